#!/usr/bin/env python3
"""Write Zenoh json5 configs for a secured deployment (standard library only).

    python deploy/zenoh/config.py server --certs DIR --listen tls/0.0.0.0:7447 r1 r2 > s.json5
    python deploy/zenoh/config.py agent --certs DIR --connect tls/server:7447 --robot r1 > a.json5
    python deploy/zenoh/config.py client --certs DIR --connect tls/server:7447 --name dashboard
    python deploy/zenoh/config.py zenohd --certs DIR --name site-b --listen tls/0.0.0.0:7447 \
        --connect tls/server:7447 r3 r4 > site-b.json5        # a site router for zenohd
    python deploy/zenoh/config.py server ... --site site-b=r3,r4 r1 r2    # and the server side
    python deploy/zenoh/config.py server ... --worker worker1 r1 r2    # a second server worker
    python deploy/zenoh/config.py client --certs DIR --connect tls/server:7447 --name worker1

The server's router requires mutual TLS and applies access control keyed on the certificate's
common name: robot <id> may publish only its scans, sightings and status
(``mrslam/robot/<id>/{scan,tags,status}``), hold only its liveliness token
(``mrslam/robot/<id>/alive``), and subscribe only to its commands
(``mrslam/robot/<id>/cmd_vel``) and to ``mrslam/server/**`` (the map, the server's liveliness).
It may never publish a command: only the server commands a robot. It is told which keys under
``mrslam/`` have subscribers (declarations only, no data): without that, a client's declared
publisher delivers its first put at most and drops the rest. Names passed with ``--observer``
(dashboards, loggers) may read everything and write nothing; names passed with ``--worker``
(the server's other worker processes, ``server.runtime.cluster``) may do what the server does.
Everything else is denied. The server's own session is the router, so its publications and
subscriptions are local and always allowed.

Several sites: robots at a remote site connect to a ``zenohd`` router there, which connects to
the server over mutual TLS with its own certificate. The site router enforces the per-robot
rules for its robots, and the server grants the site router (``--site NAME=r3,r4``) exactly the
union of its robots' rights, so no robot gains anything by being behind a site router.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

# what a remote sends into the router (ingress) and receives from it (egress)
WRITE = ["put", "delete", "declare_queryable", "liveliness_token", "reply"]
PUBLISH = ["put", "delete"]
TOKEN = ["liveliness_token"]
SUBSCRIBE = ["declare_subscriber", "query", "declare_liveliness_subscriber", "liveliness_query"]
RECEIVE = ["put", "delete", "reply", "liveliness_token", "query"]
DECLARE = ["declare_subscriber", "declare_queryable", "declare_liveliness_subscriber"]
SERVER_CN = "mrslam-server"   # make-certs.sh's common name for the server


def tls_block(certs: Path, name: str, listen: bool) -> dict[str, object]:
    block: dict[str, object] = {
        "root_ca_certificate": str(certs / "ca.pem"),
        "enable_mtls": True,
        "verify_name_on_connect": False,
    }
    side = "listen" if listen else "connect"
    block[f"{side}_private_key"] = str(certs / f"{name}.key")
    block[f"{side}_certificate"] = str(certs / f"{name}.pem")
    return block


def _rule(rid: str, flow: str, messages: list[str], keys: list[str]) -> dict[str, object]:
    return {"id": rid, "permission": "allow", "flows": [flow], "messages": messages,
            "key_exprs": keys}


def robot_keys(rid: str) -> dict[str, list[str]]:
    """What robot ``rid``'s certificate may do: publish its scans, sightings and status, hold
    its liveliness token, and read its own commands and the server's keys. Never publish on
    its ``cmd_vel``: only the server commands a robot (docs/wire.md)."""
    own = f"mrslam/robot/{rid}"
    return {"publish": [f"{own}/scan", f"{own}/tags", f"{own}/status"],
            "token": [f"{own}/alive", f"{own}/alive/**"],
            "read": [f"{own}/cmd_vel", "mrslam/server/**"]}


def access_control(robots: list[str], observers: list[str],
                   sites: dict[str, list[str]] | None = None,
                   workers: list[str] | None = None) -> dict[str, Any]:
    rules: list[dict[str, object]] = []
    subjects: list[dict[str, object]] = []
    policies: list[dict[str, object]] = []
    if workers:
        # the server's other worker processes (server.runtime.cluster) do what the server does
        everything = WRITE + SUBSCRIBE
        rules += [_rule("worker-in", "ingress", everything, ["mrslam/**"]),
                  _rule("worker-out", "egress", everything + RECEIVE, ["mrslam/**"])]
        subjects.append({"id": "workers", "cert_common_names": workers})
        policies.append({"id": "policy-workers", "subjects": ["workers"],
                         "rules": ["worker-in", "worker-out"]})
    for site, site_robots in (sites or {}).items():
        rights = [robot_keys(rid) for rid in site_robots]
        rules += _robot_rules(site, sorted({k for r in rights for k in r["publish"]}),
                              sorted({k for r in rights for k in r["token"]}),
                              sorted({k for r in rights for k in r["read"]}))
        subjects.append({"id": f"site-{site}", "cert_common_names": [site]})
        policies.append({"id": f"policy-site-{site}", "subjects": [f"site-{site}"],
                         "rules": [r["id"] for r in rules[-5:]]})
    for rid in robots:
        r = robot_keys(rid)
        rules += _robot_rules(rid, r["publish"], r["token"], r["read"])
        subjects.append({"id": f"robot-{rid}", "cert_common_names": [rid]})
        policies.append({"id": f"policy-{rid}", "subjects": [f"robot-{rid}"],
                         "rules": [r["id"] for r in rules[-5:]]})
    if observers:
        rules += [_rule("observe-subscribe", "ingress", SUBSCRIBE, ["mrslam/**"]),
                  _rule("observe-receive", "egress", RECEIVE, ["mrslam/**"])]
        subjects.append({"id": "observers", "cert_common_names": observers})
        policies.append({"id": "policy-observers", "subjects": ["observers"],
                         "rules": ["observe-subscribe", "observe-receive"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules,
            "subjects": subjects, "policies": policies}


def _robot_rules(name: str, publish: list[str], token: list[str], read: list[str]
                 ) -> list[dict[str, object]]:
    """The five rules of a robot (or of a site router, for all its robots at once)."""
    return [_rule(f"{name}-publish", "ingress", PUBLISH, publish),
            _rule(f"{name}-token", "ingress", TOKEN, token),
            _rule(f"{name}-subscribe", "ingress", SUBSCRIBE, read),
            _rule(f"{name}-receive", "egress", RECEIVE, read),
            # the server's subscriptions to the robot's keys: a client's publisher that hears
            # of no subscriber drops its puts before they leave the robot (router to router:
            # the site forwards its robots' data only where the server subscribes)
            _rule(f"{name}-routes", "egress", DECLARE, ["mrslam/**"])]


def server_config(certs: Path, listen: list[str], robots: list[str],
                  observers: list[str], sites: dict[str, list[str]] | None = None,
                  workers: list[str] | None = None) -> dict[str, object]:
    return {
        "mode": "router",
        "listen": {"endpoints": listen},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"link": {"tls": tls_block(certs, "server", listen=True)}},
        "access_control": access_control(robots, observers, sites, workers),
    }


def site_router_config(certs: Path, name: str, listen: list[str], connect: list[str],
                       robots: list[str]) -> dict[str, object]:
    """A zenohd router at a remote site: its robots connect to it, it connects to the server.

    One certificate ``name`` serves both sides (it is signed for server and client auth).
    """
    tls = tls_block(certs, name, listen=True)
    tls.update({f"connect_{k.split('_', 1)[1]}": v for k, v in tls.items()
                if k.startswith("listen_")})
    return {
        "mode": "router",
        "listen": {"endpoints": listen},
        "connect": {"endpoints": connect, "timeout_ms": -1},
        "scouting": {"multicast": {"enabled": False}},
        # a router that takes its clients' shared memory keeps every pool mapped after they
        # leave (eclipse-zenoh/zenoh#2787; docs/wire.md "Memory per session")
        "transport": {"link": {"tls": tls}, "shared_memory": {"enabled": False}},
        "access_control": upstream(access_control(robots, []), SERVER_CN),
    }


def upstream(acl: dict[str, Any], common_name: str) -> dict[str, Any]:
    """Let everything under mrslam/ pass to and from the router holding ``common_name``."""
    everything = WRITE + SUBSCRIBE
    acl["rules"] += [_rule("upstream-in", "ingress", everything, ["mrslam/**"]),
                     _rule("upstream-out", "egress", everything, ["mrslam/**"])]
    acl["subjects"].append({"id": "upstream", "cert_common_names": [common_name]})
    acl["policies"].append({"id": "policy-upstream", "subjects": ["upstream"],
                            "rules": ["upstream-in", "upstream-out"]})
    return acl


def client_config(certs: Path, connect: list[str], name: str) -> dict[str, object]:
    return {
        "mode": "client",
        "connect": {"endpoints": connect, "timeout_ms": -1},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"link": {"tls": tls_block(certs, name, listen=False)}},
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("role", choices=["server", "agent", "client", "zenohd"])
    ap.add_argument("--certs", type=Path, required=True, help="folder from make-certs.sh")
    ap.add_argument("--listen", action="append", default=[])
    ap.add_argument("--connect", action="append", default=[])
    ap.add_argument("--robot", help="robot id (agent)")
    ap.add_argument("--name", help="certificate name (client, zenohd)")
    ap.add_argument("--site", action="append", default=[], metavar="NAME=R1,R2",
                    help="a site router and the robots behind it (server)")
    ap.add_argument("--observer", action="append", default=[],
                    help="certificate name allowed to read everything (server)")
    ap.add_argument("--worker", action="append", default=[],
                    help="certificate name of another worker of the server, allowed what the "
                    "server does (server; docs/scale.md)")
    ap.add_argument("robots", nargs="*", help="robot ids (server)")
    a = ap.parse_intermixed_args(argv)
    if a.role == "server":
        sites: dict[str, list[str]] = {}
        for spec in a.site:
            name, _, ids = spec.partition("=")
            if not name or not ids:
                ap.error(f"--site {spec!r}: expected NAME=R1,R2")
            sites[name] = [r for r in ids.split(",") if r]
        conf = server_config(a.certs, a.listen or ["tls/0.0.0.0:7447"], a.robots, a.observer,
                             sites, a.worker)
    elif a.role == "zenohd":
        if not a.name or not a.connect:
            ap.error("zenohd needs --name (its certificate) and --connect (the server)")
        conf = site_router_config(a.certs, a.name, a.listen or ["tls/0.0.0.0:7447"],
                                  a.connect, a.robots)
    else:
        name = a.robot if a.role == "agent" else a.name
        if not name:
            ap.error("--robot (agent) or --name (client) is required")
        conf = client_config(a.certs, a.connect or ["tls/127.0.0.1:7447"], name)
    json.dump(conf, sys.stdout, indent=2)
    sys.stdout.write("\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
