"""The effects file (baton.effects): one line per effect, continued after a restart."""

from __future__ import annotations

import json
from pathlib import Path

from baton.effects import EffectsFile, read_effects


def test_each_effect_is_one_line_on_disk_at_once(tmp_path: Path) -> None:
    path = tmp_path / "effects.jsonl"
    effects = EffectsFile(path)
    assert effects.record("picture", resolution="16x16", bytes=783) == 1
    # On disk already, with nothing closed or flushed by the reader's side.
    (line,) = path.read_text().splitlines()
    assert json.loads(line) == {
        "seq": 1,
        "time": json.loads(line)["time"],
        "effect": "picture",
        "resolution": "16x16",
        "bytes": 783,
    }
    assert effects.record("picture", resolution="16x16", bytes=783) == 2
    assert [e["seq"] for e in read_effects(path)] == [1, 2]


def test_a_restarted_writer_continues_the_sequence_after_a_torn_line(tmp_path: Path) -> None:
    path = tmp_path / "effects.jsonl"
    first = EffectsFile(path)
    first.record("arm")
    first.record("takeoff", relative_altitude_m=5.0)
    with path.open("a") as out:
        out.write('{"seq": 3, "time": 1.0, "eff')  # killed while writing
    again = EffectsFile(path)
    assert again.record("land") == 3
    assert [(e["seq"], e["effect"]) for e in read_effects(path)] == [
        (1, "arm"),
        (2, "takeoff"),
        (3, "land"),
    ]


def test_without_a_file_it_counts_in_memory_and_writes_nothing(tmp_path: Path) -> None:
    effects = EffectsFile(None)
    assert effects.record("arm") == 1 and effects.seq == 1
    assert read_effects(tmp_path / "never-written.jsonl") == []
    assert list(tmp_path.iterdir()) == []
