"""The testbed file's model: every bad value is refused with the file, the field and
what to write instead (issue 11's list of inputs that were crashes or silently wrong)."""

from __future__ import annotations

from typing import Any

import pytest

from baton.config import ConfigError, parse_config, parse_duration, parse_size

TWO: list[dict[str, Any]] = [
    {"id": 0, "address": "127.0.0.1:7100"},
    {"id": 1, "address": "127.0.0.1:7101"},
]


def refused(document: dict[str, Any]) -> str:
    with pytest.raises(ConfigError) as error:
        parse_config(document, "t.yaml")
    return str(error.value)


@pytest.mark.parametrize(
    ("extra", "field", "why"),
    [
        ({"flush_limit": float("inf")}, "flush_limit", "finite"),
        ({"flush_limit": "1e999"}, "flush_limit", "finite"),
        ({"flush_limit": float("nan")}, "flush_limit", "finite"),
        ({"controller_link": {"latency": float("inf")}}, "controller_link.latency", "finite"),
        ({"controller_link": {"latency": float("nan")}}, "controller_link.latency", "finite"),
        ({"drone_link": {"bandwidth": float("nan")}}, "drone_link.bandwidth", "finite"),
        ({"drone_link": {"latency": "2days"}}, "drone_link.latency", "units"),
        ({"takeover_after": 10**9}, "takeover_after", "at most"),
        ({"speedup": float("nan")}, "speedup", ""),
    ],
)
def test_numbers_that_are_not_finite_or_not_sane_are_refused(
    extra: dict[str, Any], field: str, why: str
) -> None:
    message = refused({"controllers": TWO, **extra})
    assert message.startswith(f"t.yaml: {field}: "), message
    assert why in message


def test_a_boolean_is_not_an_id() -> None:
    message = refused({"controllers": [{"id": True, "address": "127.0.0.1:7100"}]})
    assert message.startswith("t.yaml: controllers[0].id: ")
    assert "integer" in message


def test_two_parts_on_one_address_are_refused() -> None:
    twins = [{"id": 0, "address": "127.0.0.1:7100"}, {"id": 1, "address": "127.0.0.1:7100"}]
    message = refused({"controllers": twins})
    assert "127.0.0.1:7100" in message and "controllers 0 and 1" in message
    clash = refused({"controllers": TWO, "drone": {"address": "127.0.0.1:7101"}})
    assert "127.0.0.1:7101" in clash and "drone" in clash
    # Port 0 picks a free port for each: not a clash.
    parse_config({"controllers": [{"id": c, "address": "127.0.0.1:0"} for c in (0, 1)]})


def test_the_parsers_refuse_infinity_for_flags_too() -> None:
    for parse, text in ((parse_size, "1e999"), (parse_duration, "1e999"), (parse_size, "1e999MB")):
        with pytest.raises(ValueError, match="finite"):
            parse(text)


def test_a_handover_policy_needs_every_controllers_location_and_range() -> None:
    placed = [
        {**TWO[0], "location": {"latitude_deg": 47.0, "longitude_deg": 8.0}, "range_m": 500},
        {**TWO[1], "location": {"latitude_deg": 47.0, "longitude_deg": 8.01}},
    ]
    assert "controller 1 has no range_m" in refused(
        {"controllers": placed, "handover_policy": "nearest"}
    )
    assert "handover_policy.name: Input should be 'none', 'nearest' or 'predictive'" in refused(
        {"controllers": TWO, "handover_policy": "closest"}
    )
    placed[1]["range_m"] = 500
    config = parse_config(
        {"controllers": placed, "handover_policy": {"name": "predictive", "lead": "20s"}}
    )
    assert (config.handover_policy.name, config.handover_policy.lead) == ("predictive", 20.0)
    assert parse_config({"controllers": TWO}).handover_policy.name == "none"


def test_a_radio_fade_needs_radio_range_and_sane_numbers() -> None:
    placed = [
        {**c, "location": {"latitude_deg": 47.0, "longitude_deg": 8.0 + c["id"] / 100}} for c in TWO
    ]
    placed = [{**c, "range_m": 500} for c in placed]
    assert "radio_fade fades the radio range's links: set radio_range: true" in refused(
        {"controllers": placed, "radio_fade": {}}
    )
    assert "radio_fade.bandwidth_factor" in refused(
        {"controllers": placed, "radio_range": True, "radio_fade": {"bandwidth_factor": 0}}
    )
    config = parse_config(
        {"controllers": placed, "radio_range": True, "radio_fade": {"latency": "50ms"}}
    )
    assert config.radio_fade is not None and config.radio_fade.link_arg() == "0.8,0.05s,0.25"
    assert parse_config({"controllers": placed, "radio_range": True}).radio_fade is None


@pytest.mark.parametrize(
    ("safety", "field", "why"),
    [
        ({"lost_link": -1}, "safety.lost_link", ">= 0"),
        ({"lost_link": float("nan")}, "safety.lost_link", "finite"),
        ({"lost_link_action": "crash"}, "safety.lost_link_action", "nearest_station"),
        ({"battery_reserve": -5}, "safety.battery_reserve", "greater than or equal to 0"),
        ({"battery_reserve": float("nan")}, "safety.battery_reserve", "finite"),
        ({"battery_reserve": 150}, "safety.battery_reserve", "less than or equal to 100"),
        ({"battery_action": "hold"}, "safety.battery_action", "rtl"),
        ({"max_speed": 0}, "safety.max_speed", "greater than 0"),
        ({"max_sleep": float("inf")}, "safety.max_sleep", "finite"),
        ({"lost_link": 2}, "", "must be longer than takeover_after"),
    ],
)
def test_the_safety_net_s_bad_values_are_refused(
    safety: dict[str, Any], field: str, why: str
) -> None:
    message = refused({"controllers": TWO, "safety": safety})
    assert "t.yaml" in message and field in message and why in message, message


def test_the_safety_net_s_defaults() -> None:
    safety = parse_config({"controllers": TWO}).safety
    assert (safety.lost_link, safety.lost_link_action) == (30.0, "rtl")
    assert (safety.battery_reserve, safety.battery_action) == (20.0, "rtl")
    assert (safety.max_speed, safety.max_altitude, safety.max_sleep) == (15.0, 120.0, 600.0)
