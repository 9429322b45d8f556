"""How much memory a Zenoh router keeps for each client session that sent large payloads.

A router process listens on loopback. Client sessions, each in its own process, one after
another, connect, put M payloads of S bytes on a key nobody subscribes to, and close. The
router's memory is read from ``/proc/<pid>/status`` before the first session and after the
last one. Printed as JSON, one entry per variant of the router's config:

- ``zenoh-default``: Zenoh's defaults (shared memory on);
- ``no-shm``: the same with ``transport/shared_memory/enabled: false`` on the router;
- ``mrslam``: the router config mrslam's server uses (``schemas.bus.zenoh_config``); the
  only variant that needs this repository, imported only when asked for.

What it shows with eclipse-zenoh 1.10 on Linux, run as root (or with a memlock limit above
16 MiB): with shared memory on, a client on the same host negotiates it with the router, and
from its second large payload on (the first one sets up its 16 MiB pool, in the background)
sends descriptors into that pool. The router maps and locks the client's pool (16 MiB) and
metadata segment (1.25 MiB) and never unmaps them, also after the client process exits, so
``RssShmem``/``VmLck`` grow by ~17 MiB per such session (eclipse-zenoh/zenoh#2787, #1700).
With shared memory off on the router, nothing is negotiated and the router stays flat.

Plain Zenoh only in the reproduction (``--variant mrslam`` aside), so it can be handed to
Zenoh's maintainers as it is::

    python zenoh_session_memory.py --sessions 100 --messages 2 --size 2000000
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import platform
import resource
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from importlib import metadata
from pathlib import Path
from typing import Any

VARIANTS = ("zenoh-default", "no-shm", "mrslam")
KEY = "nobody/listens/here"
_FIELDS = ("VmRSS", "RssAnon", "RssFile", "RssShmem", "VmLck")


# -- measuring a process ----------------------------------------------------------------------
def memory_mb(pid: int) -> dict[str, float]:
    """The memory fields of ``/proc/<pid>/status`` in MB (RSS, its parts, locked)."""
    out: dict[str, float] = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        name, _, value = line.partition(":")
        if name in _FIELDS:
            out[name] = round(int(value.split()[0]) / 1024, 1)
    return out


def zenoh_shm_mappings(pid: int) -> int:
    """How many Zenoh shared-memory segments (``/dev/shm/*.zenoh``) the process maps."""
    lines = Path(f"/proc/{pid}/maps").read_text().splitlines()
    return sum(1 for line in lines if line.endswith(".zenoh") and "/dev/shm/" in line)


# -- the two roles, run in their own processes ------------------------------------------------
def _config(mode: str, endpoint: str, settings: list[str], variant: str) -> Any:
    import zenoh

    if variant == "mrslam":
        conf = _mrslam_router_config(endpoint)
    else:
        conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps(mode))
        key = "listen/endpoints" if mode == "router" else "connect/endpoints"
        conf.insert_json5(key, json.dumps([endpoint]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        if variant == "no-shm":
            conf.insert_json5("transport/shared_memory/enabled", "false")
    for setting in settings:
        key, _, value = setting.partition("=")
        conf.insert_json5(key, value)
    return conf


def _mrslam_router_config(endpoint: str) -> Any:
    # the one non-Zenoh import, only for --variant mrslam: the server's own router config
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    from schemas.bus import zenoh_config

    return zenoh_config("router", [endpoint])


def _router(endpoint: str, settings: list[str], variant: str) -> None:
    """Listen; on stdin ``trim`` gives freed heap back to the OS (glibc), ``quit`` closes."""
    import zenoh

    session = zenoh.open(_config("router", endpoint, settings, variant))
    print("ready", flush=True)
    for line in sys.stdin:
        if line.strip() == "trim":
            ctypes.CDLL("libc.so.6").malloc_trim(0)
            print("trimmed", flush=True)
        elif line.strip() == "quit":
            break
    session.close()


def _client(endpoint: str, settings: list[str], messages: int, size: int) -> None:
    import zenoh

    session = zenoh.open(_config("client", endpoint, settings, "zenoh-default"))
    payload = os.urandom(size)
    for _ in range(messages):
        session.put(KEY, payload, congestion_control=zenoh.CongestionControl.BLOCK)
    time.sleep(0.1)   # let the last put leave before the session closes
    session.close()


# -- one measured run ---------------------------------------------------------------------------
def _free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def _child(*args: str) -> list[str]:
    return [sys.executable, str(Path(__file__).resolve()), *args]


def run(variant: str, sessions: int, messages: int, size: int, *,
        router_set: Sequence[str] = (), client_set: Sequence[str] = (),
        router_env: dict[str, str] | None = None, trim: bool = False,
        settle_s: float = 1.0) -> dict[str, Any]:
    """Start a router, run ``sessions`` client processes one after another, measure."""
    endpoint = _free_endpoint()
    sets = [a for s in router_set for a in ("--set", s)]
    router = subprocess.Popen(
        _child("--role", "router", "--endpoint", endpoint, "--variant", variant, *sets),
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
        env={**os.environ, **(router_env or {})})
    assert router.stdin is not None and router.stdout is not None
    try:
        if router.stdout.readline().strip() != "ready":
            raise RuntimeError(f"the router did not start (exit {router.wait()})")
        time.sleep(0.5)
        before = memory_mb(router.pid)
        client_sets = [a for s in client_set for a in ("--set", s)]
        series: list[float] = []
        t0 = time.monotonic()
        for i in range(sessions):
            subprocess.run(_child("--role", "client", "--endpoint", endpoint,
                                  "--messages", str(messages), "--size", str(size),
                                  *client_sets), check=True, timeout=60)
            if (i + 1) % max(1, sessions // 10) == 0:
                series.append(memory_mb(router.pid)["VmRSS"])
        seconds = time.monotonic() - t0
        time.sleep(settle_s)   # memory still held now is kept, not in flight
        after = memory_mb(router.pid)
        result: dict[str, Any] = {
            "variant": variant, "router_set": list(router_set),
            "client_set": list(client_set), "router_env": router_env or {},
            "before_mb": before, "after_mb": after,
            "growth_mb": round(after["VmRSS"] - before["VmRSS"], 1),
            "growth_per_session_mb": round((after["VmRSS"] - before["VmRSS"]) / sessions, 2),
            "zenoh_shm_mappings_after": zenoh_shm_mappings(router.pid),
            "rss_every_tenth_mb": series, "seconds": round(seconds, 1),
        }
        if trim:
            router.stdin.write("trim\n")
            router.stdin.flush()
            router.stdout.readline()
            result["after_malloc_trim_mb"] = memory_mb(router.pid)
        router.stdin.write("quit\n")
        router.stdin.flush()
        router.wait(timeout=10)
        return result
    finally:
        if router.poll() is None:
            router.kill()
            router.wait()


def environment() -> dict[str, Any]:
    soft, _ = resource.getrlimit(resource.RLIMIT_MEMLOCK)
    return {"eclipse_zenoh": metadata.version("eclipse-zenoh"),
            "python": platform.python_version(), "kernel": platform.release(),
            "uid": os.getuid(),
            "memlock_limit_bytes": None if soft == resource.RLIM_INFINITY else soft}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        description="Memory a Zenoh router keeps per client session that sent large "
                    "payloads (client sessions in separate processes, one after another). "
                    "Prints JSON.")
    p.add_argument("--sessions", type=int, default=30, help="client sessions (default 30)")
    p.add_argument("--messages", type=int, default=2, help="puts per session (default 2)")
    p.add_argument("--size", type=int, default=2_000_000, help="bytes per put (default 2 MB)")
    p.add_argument("--variant", action="append", choices=VARIANTS,
                   help="router config, repeatable (default: zenoh-default and no-shm)")
    p.add_argument("--router-set", action="append", default=[], metavar="KEY=JSON5",
                   help="one more router setting, e.g. transport/link/rx/buffer_size=16384")
    p.add_argument("--client-set", action="append", default=[], metavar="KEY=JSON5",
                   help="one more client setting")
    p.add_argument("--router-env", action="append", default=[], metavar="NAME=VALUE",
                   help="environment of the router, e.g. MALLOC_ARENA_MAX=2")
    p.add_argument("--trim", action="store_true",
                   help="also measure after glibc malloc_trim(0) in the router")
    p.add_argument("--settle", type=float, default=1.0,
                   help="seconds to wait after the last session (default 1)")
    # the roles this program runs itself as
    p.add_argument("--role", choices=("router", "client"), help=argparse.SUPPRESS)
    p.add_argument("--endpoint", help=argparse.SUPPRESS)
    p.add_argument("--set", action="append", default=[], help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.role == "router":
        _router(a.endpoint, a.set, (a.variant or ["zenoh-default"])[0])
        return 0
    if a.role == "client":
        _client(a.endpoint, a.set, a.messages, a.size)
        return 0
    env = dict(e.split("=", 1) for e in a.router_env)
    runs = [run(v, a.sessions, a.messages, a.size, router_set=a.router_set,
                client_set=a.client_set, router_env=env, trim=a.trim, settle_s=a.settle)
            for v in (a.variant or ["zenoh-default", "no-shm"])]
    print(json.dumps({"environment": environment(), "sessions": a.sessions,
                      "messages": a.messages, "size": a.size, "runs": runs}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
