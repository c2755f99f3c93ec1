"""The campaign's Zenoh control cases (issue 20): hostile sessions against the live runtime's stop
and reset queryables, while the arm runs (docs/faults.md, docs/security.md "Zenoh").

- ``zenoh_control_unauthenticated``: sessions without credentials, and with a wrong password, send
  stop and reset (exact keys and wildcards): the runtime's session refuses them at the handshake;
  no reply, the loop stays ACTIVE.
- ``zenoh_control_wildcard``: an authenticated session sends ``hil/<robot>/**``, ``hil/*/stop``,
  ``hil/<robot>/re$*``...: only schema/config/bundle answer; stop and reset refuse every key
  expression that is not exactly theirs (counted), the loop stays ACTIVE.

The runtime runs with ``telemetry.controls_enabled`` and ``auth.users_file``; the campaign's own
telemetry watch has no credentials, so these cases judge by the runtime's state, not its events.
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from models.lab.faults import cases as c
from models.lab.faults.cases import Expect

ROBOT = "ur5_paper"
OPERATOR = ("operator", "campaign-s3cret")
CONTROL_KEYS = (f"hil/{ROBOT}/stop", f"hil/{ROBOT}/reset")
WILDCARDS = (
    f"hil/{ROBOT}/**",
    "hil/*/stop",
    "hil/*/reset",
    f"hil/{ROBOT}/re$*",
    f"hil/{ROBOT}/st$*",
    "hil/**",
    f"hil/{ROBOT}/*",
)


class ControlProbe:
    """Queries sent from a thread (the loop must keep running while Zenoh waits for replies)."""

    def __init__(self, credentials: tuple[tuple[str, str] | None, ...], keys: tuple[str, ...]) -> None:
        self.credentials = credentials
        self.keys = keys
        self.replies: dict[str, list[tuple[str, str]]] = {}
        self.error: str | None = None
        self._thread: threading.Thread | None = None

    def inject(self, rig: Any, rng: np.random.Generator) -> dict[str, Any]:
        endpoint = f"tcp/127.0.0.1:{rig.telemetry_port}"
        self._thread = threading.Thread(target=self._run, args=(endpoint,), name="zenoh-probe", daemon=True)
        self._thread.start()
        users = ["none" if who is None else who[0] for who in self.credentials]
        return {"sessions": users, "keys": list(self.keys)}

    def _run(self, endpoint: str) -> None:
        try:
            for who in self.credentials:
                label = "none" if who is None else f"{who[0]}:{'ok' if who == OPERATOR else 'wrong'}"
                for key, replies in _gets(endpoint, self.keys, who).items():
                    self.replies[f"{label} {key}"] = replies
        except Exception as exc:  # noqa: BLE001 - reported as the case's failure
            self.error = f"{type(exc).__name__}: {exc}"

    def check(self, rig: Any, result: c.CaseResult) -> None:
        """After the observation: every query answered or timed out, the runtime untouched."""
        from hil_runtime.lifecycle import LifecycleState

        if self._thread is not None:
            self._thread.join(30.0)
        if self.error is not None:
            result.failures.append(f"probe: {self.error}")
        accepted = {
            query: [body for kind, body in replies if kind == "ok" and '"request"' in body]
            for query, replies in self.replies.items()
        }
        accepted = {query: bodies for query, bodies in accepted.items() if bodies}
        answered = sum(1 for replies in self.replies.values() if replies)
        refused = int(getattr(rig.runtime.telemetry, "refused_controls", 0))
        result.detail["queries"] = len(self.replies)
        result.detail["queries_answered"] = answered
        result.detail["control_refusals_counted"] = refused
        result.detail["controls_accepted"] = accepted
        if accepted:
            result.failures.append(f"a control acted on {sorted(accepted)}")
        if rig.runtime.state is not LifecycleState.ACTIVE or not rig.loop.alive:
            result.failures.append(f"the runtime left ACTIVE ({rig.runtime.state.value})")


def _gets(endpoint: str, keys: tuple[str, ...], who: tuple[str, str] | None) -> dict[str, list[tuple[str, str]]]:
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    if who is not None:
        conf.insert_json5("transport/auth/usrpwd/user", json.dumps(who[0]))
        conf.insert_json5("transport/auth/usrpwd/password", json.dumps(who[1]))
    session = zenoh.open(conf)
    try:
        time.sleep(0.3)  # the link comes up, or is refused at the handshake
        pending = {key: session.get(key, timeout=1.0, target=zenoh.QueryTarget.ALL) for key in keys}
        out: dict[str, list[tuple[str, str]]] = {}
        for key, replies in pending.items():
            out[key] = [
                ("ok", r.ok.payload.to_string()) if r.ok is not None else ("err", _error_text(r)) for r in replies
            ]
        return out
    finally:
        session.close()


def _error_text(reply: Any) -> str:
    return str(reply.err.payload.to_string()) if reply.err is not None else ""


def _controlled_case(probe: ControlProbe) -> Any:
    def run(name: str, repeat: int, seed: int, work: Path) -> c.CaseResult:
        from hil_runtime.telemetry.auth import write_users_file

        users = write_users_file(work / "zenoh-users", {OPERATOR[0]: OPERATOR[1]})
        telemetry = {"controls_enabled": True, "auth": {"users_file": str(users)}}
        result = c.run_in_process(
            name,
            repeat,
            seed,
            probe.inject,
            Expect(event=False, max_cycles=None),
            config_extra={"telemetry": telemetry},
            watch_telemetry=False,  # the campaign's watch has no credentials: judged by the runtime's state
            observe_cycles=1500,
            post_check=probe.check,
        )
        detail = result.detail
        result.action = (
            f"refused: {detail.get('queries', 0)} queries, {detail.get('queries_answered', 0)} answered "
            f"(schema/config/bundle or an error), {len(detail.get('controls_accepted') or {})} reached a control, "
            f"{detail.get('control_refusals_counted', 0)} counted as refused"
        )
        return result

    return run


def unauthenticated_control(name: str, repeat: int, seed: int, work: Path) -> c.CaseResult:
    probe = ControlProbe((None, (OPERATOR[0], "wrong")), (*CONTROL_KEYS, *WILDCARDS))
    return _controlled_case(probe)(name, repeat, seed, work)


def wildcard_control(name: str, repeat: int, seed: int, work: Path) -> c.CaseResult:
    probe = ControlProbe((OPERATOR,), WILDCARDS)
    result = _controlled_case(probe)(name, repeat, seed, work)
    if result.detail.get("control_refusals_counted", 0) == 0:
        result.failures.append("no wildcard query was counted as refused (did any reach the controls?)")
        result.passed = False
    return result
