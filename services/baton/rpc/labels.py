"""The words people and reports read for the contracts' enum values.

A status field whose values are a closed set is an enum in the contracts
(``ControllerStatus.state``, ``HandoverRecord.kind``, ``PolicyDecision.action``,
...), and code assigns and compares the generated values
(``drone_pb2.HANDOVER_KIND_TAKEOVER``), never strings. What people read (the
terminal, the logs, the JSON report and so the docs) are words: ``label``
is the one place that turns a value into its word, the value's name without
its enum's prefix in lower case (``"takeover"``, ``"fly_on"``), except a
controller state, which keeps the paper's capitals (``"ACTIVE"``). ``parse``
is its inverse, for a word that comes from a file or a flag (the testbed
file's ``handover_policy``).
"""

from __future__ import annotations

from typing import Protocol, TypeVar

from google.protobuf.descriptor import EnumDescriptor

from baton.v1 import ring_pb2

V_co = TypeVar("V_co", bound=int, covariant=True)

# Enums whose words keep their capitals: the paper's names (Figure 3).
_CAPITALS = frozenset({ring_pb2.ControllerState.DESCRIPTOR.full_name})


class EnumType(Protocol[V_co]):
    """A generated enum (``drone_pb2.HandoverKind``): its descriptor and values."""

    @property
    def DESCRIPTOR(self) -> EnumDescriptor: ...

    def Value(self, name: str) -> V_co: ...


def _prefix(enum: EnumDescriptor) -> str:
    # Every enum's 0 is <PREFIX>UNSPECIFIED (the style guide's prefixed values).
    return enum.values_by_number[0].name.removesuffix("UNSPECIFIED")


def label(enum: EnumType[int], value: int) -> str:
    """The word for ``value`` of ``enum``: ``label(drone_pb2.HandoverKind, 3) == "takeover"``.

    A number the contracts do not name (a newer peer's) reads as that number.
    """
    descriptor = enum.DESCRIPTOR
    named = descriptor.values_by_number.get(value)
    if named is None:
        return str(value)
    word = named.name.removeprefix(_prefix(descriptor))
    return word if descriptor.full_name in _CAPITALS else word.lower()


def parse(enum: EnumType[V_co], word: str) -> V_co:
    """The value of ``enum`` whose word is ``word`` (``label``'s inverse)."""
    descriptor = enum.DESCRIPTOR
    prefix = _prefix(descriptor)
    if word.upper() != "UNSPECIFIED" and f"{prefix}{word.upper()}" in descriptor.values_by_name:
        value = enum.Value(f"{prefix}{word.upper()}")
        if label(enum, value) == word:
            return value
    words = [label(enum, v.number) for v in descriptor.values if v.number != 0]
    raise ValueError(f"unknown {descriptor.name} {word!r}; use one of {', '.join(words)}")
