"""The pure decisions about a durable file that fails a write (``baton.durability``)."""

from __future__ import annotations

import grpc

from baton.durability import FileHealth, drone_refusal, write_failed, write_succeeded


def test_a_failure_is_reported_once_with_its_delay_and_the_rest_are_counted() -> None:
    health = FileHealth("/data/c1.sqlite")
    failed, reports = write_failed(
        health, "a checkpoint", "disk full", 10.4, "it keeps the rest in memory", 11, began=10.0
    )
    [report] = reports
    assert report.level == "error"
    assert report.text == (
        "cannot write /data/c1.sqlite: a checkpoint failed: disk full; it keeps the rest in memory"
    )
    assert report.fields["said_after_s"] == 0.4
    assert (failed.durable, failed.whole_up_to, failed.failed_at, failed.failures) == (
        False,
        11,
        10.0,
        1,
    )
    again, reports = write_failed(failed, "log message 13", "disk full", 11.0, "", 12)
    assert reports == [] and again.failures == 2
    assert (again.failed_write, again.whole_up_to) == ("a checkpoint", 11)  # the first's


def test_a_write_that_succeeds_after_failures_makes_the_file_durable_again() -> None:
    health = FileHealth("/data/drone.sqlite")
    assert write_succeeded(health, 5.0) == (health, [])
    assert drone_refusal(health) is None
    failed, _ = write_failed(health, "request 3", "I/O error", 5.0, "refusing")
    refusal = drone_refusal(failed)
    assert refusal is not None and refusal.code is grpc.StatusCode.UNAVAILABLE
    assert refusal.message.startswith(
        "the drone cannot write its state file /data/drone.sqlite: I/O error; it refuses new "
        "requests so that none can be executed twice after a restart"
    )
    recovered, [report] = write_succeeded(failed, 7.5)
    assert recovered == health and report.level == "info"
    assert report.fields == {"file": "/data/drone.sqlite", "failed_writes": 1, "failed_for_s": 2.5}
