"""A baton process that serves gRPC and starts processes (a controller its mission
program, the testbed its parts) starts every one intact.

uvloop starts a process with fork(); gRPC's fork handlers then run in the child
and, when another thread is inside gRPC at that moment, leave the child's copy of
gRPC inconsistent: now and then the child dies of SIGSEGV or SIGABRT before it
reaches exec. A controller reported its mission failed that way ("mission
program exited with code -6", CI, 2026-11-27). Every baton process enters
through ``baton.cli``, which turns those handlers off (docs/design.md, "Starting
processes beside gRPC").
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

SPAWNS = 1000

# Imports baton.cli first, as `baton ...` and `python -m baton.cli ...` do, then
# keeps gRPC busy on uvloop (four callers, one server) while starting /bin/true
# SPAWNS times, and prints how the abnormal ones ended.
_CHILD = textwrap.dedent(
    """
    import baton.cli
    import asyncio, json, sys
    import grpc
    from grpc_health.v1 import health, health_pb2, health_pb2_grpc
    from baton.lifecycle import run

    async def main(spawns):
        server = grpc.aio.server()
        health_pb2_grpc.add_HealthServicer_to_server(health.aio.HealthServicer(), server)
        port = server.add_insecure_port("127.0.0.1:0")
        await server.start()
        done = asyncio.Event()

        async def caller():
            async with grpc.aio.insecure_channel(f"127.0.0.1:{port}") as channel:
                stub = health_pb2_grpc.HealthStub(channel)
                while not done.is_set():
                    await stub.Check(health_pb2.HealthCheckRequest())

        callers = [asyncio.create_task(caller()) for _ in range(4)]
        abnormal = {}
        for _ in range(spawns):
            process = await asyncio.create_subprocess_exec("/bin/true")
            code = await process.wait()
            if code != 0:
                abnormal[code] = abnormal.get(code, 0) + 1
        done.set()
        await asyncio.gather(*callers)
        await server.stop(None)
        return {"loop": type(asyncio.get_running_loop()).__module__, "abnormal": abnormal}

    print(json.dumps(run(main(int(sys.argv[1])))))
    """
)


def test_processes_started_beside_busy_grpc_on_uvloop_all_start() -> None:
    done = subprocess.run(
        [sys.executable, "-c", _CHILD, str(SPAWNS)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads(done.stdout.splitlines()[-1])
    assert result["loop"].startswith("uvloop"), result
    assert result["abnormal"] == {}, (
        f"of {SPAWNS} processes started, these ended abnormally (exit code: count): "
        f"{result['abnormal']}"
    )


def test_baton_cli_turns_grpc_fork_handlers_off_before_grpc_loads() -> None:
    probe = (
        "import os, sys; import baton.cli; "
        "print(os.environ.get('GRPC_ENABLE_FORK_SUPPORT'), 'grpc' in sys.modules)"
    )
    env = {k: v for k, v in os.environ.items() if k != "GRPC_ENABLE_FORK_SUPPORT"}
    done = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, env=env, check=True
    )
    assert done.stdout.split() == ["0", "False"]
