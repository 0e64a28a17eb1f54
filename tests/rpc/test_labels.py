"""The words of the contracts' enum values (baton.rpc.labels): what reports and terminals print."""

from __future__ import annotations

import pytest

from baton.controller.protocol import State
from baton.rpc.labels import EnumType, label, parse
from baton.v1 import drone_pb2, ring_pb2


def test_a_label_is_the_value_name_after_its_prefix_in_lower_case() -> None:
    assert label(drone_pb2.HandoverKind, drone_pb2.HANDOVER_KIND_TAKEOVER) == "takeover"
    assert label(drone_pb2.HandoverTrigger, drone_pb2.HANDOVER_TRIGGER_SCRIPT) == "script"
    assert label(drone_pb2.PolicyAction, drone_pb2.POLICY_ACTION_FLY_ON) == "fly_on"
    assert label(ring_pb2.HandoverRole, ring_pb2.HANDOVER_ROLE_TAKER) == "taker"
    assert label(ring_pb2.MissionState, ring_pb2.MISSION_STATE_NONE) == "none"
    assert label(drone_pb2.HandoverPolicy, drone_pb2.HANDOVER_POLICY_NEAREST) == "nearest"


def test_a_controller_state_keeps_the_papers_capitals() -> None:
    assert [label(ring_pb2.ControllerState, s.value) for s in State] == [s.name for s in State]
    assert [s.name for s in State] == ["ACTIVE", "PASSIVE", "REPLAY"]


def test_a_number_the_contracts_do_not_name_reads_as_the_number() -> None:
    assert label(drone_pb2.HandoverKind, 99) == "99"


@pytest.mark.parametrize(
    "enum",
    [
        drone_pb2.HandoverKind,
        drone_pb2.HandoverTrigger,
        drone_pb2.PolicyAction,
        drone_pb2.HandoverPolicy,
        ring_pb2.ControllerState,
        ring_pb2.MissionState,
        ring_pb2.HandoverRole,
    ],
)
def test_parse_is_the_inverse_of_label_for_every_named_value(enum: EnumType[int]) -> None:
    values = [v.number for v in enum.DESCRIPTOR.values if v.number != 0]
    assert values, enum.DESCRIPTOR.name
    assert [parse(enum, label(enum, v)) for v in values] == values


def test_parse_refuses_a_word_it_does_not_know_naming_the_ones_it_does() -> None:
    with pytest.raises(ValueError, match="unknown HandoverPolicy 'closest'; use one of none, "):
        parse(drone_pb2.HandoverPolicy, "closest")
    with pytest.raises(ValueError, match="unknown HandoverPolicy 'unspecified'"):
        parse(drone_pb2.HandoverPolicy, "unspecified")
    with pytest.raises(ValueError, match="unknown HandoverKind 'TAKEOVER'"):
        parse(drone_pb2.HandoverKind, "TAKEOVER")  # the word is "takeover"
