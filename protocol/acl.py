"""Who may say what: the Zenoh access control every robot of a TLS swarm loads.

Each robot's session filters what arrives on each of its links by the common name of the
certificate the peer at the other end presented (``protocol.pki``): deny by default, then

- robot ``i`` (CN ``robot-<i>``) may put only its own keys (``theta/<i>/*/*``, ``status/<i>``),
  serve and answer only its own queryables (``latest/<i>``, ``keyframes/<i>``) and hold only its
  own liveliness token (``alive/<i>``);
- every robot and the monitor (CN ``monitor``) may subscribe and query anything of the swarm,
  and receive anything of the swarm (egress);
- the monitor may not put, reply, serve or declare a token: it only watches;
- a CN that is not listed (a revoked robot, a robot of another roster) matches no subject: every
  message in either direction is denied, it is admitted to the link and told nothing.

A robot with a valid certificate therefore cannot speak as another: its put on ``theta/3/...``
is dropped by the receiving robot's session before any callback runs. This relies on peers
exchanging data directly (Zenoh's ``peer_to_peer`` routing, dinerf's default: a peer does not
forward one peer's puts to another), so that the link a message arrives on is its author's.

Used as ``zenoh_settings()["access_control"]`` (``protocol.transport``). Pure Python.
"""

from __future__ import annotations

from typing import Any

from protocol.keys import Keys
from protocol.pki import MONITOR_NAME, robot_name

#: Zenoh ACL message kinds (eclipse-zenoh 1.x).
SPEAK = ("put",)
SERVE = ("declare_queryable", "reply")
TOKEN = ("liveliness_token",)
LISTEN = ("declare_subscriber", "query", "declare_liveliness_subscriber", "liveliness_query")
ALL = SPEAK + ("delete",) + SERVE + TOKEN + LISTEN


def _rule(rule_id: str, messages: tuple[str, ...], keys: list[str], flow: str = "ingress") -> dict[str, Any]:
    return {"id": rule_id, "permission": "allow", "flows": [flow], "messages": list(messages), "key_exprs": keys}


def access_control(keys: Keys, robots: list[int], revoked: list[str] = (), monitor: bool = True) -> dict[str, Any]:
    """The ``access_control`` section of a Zenoh config for a swarm of ``robots`` (ids), denying
    the identities in ``revoked`` (CNs) everything."""
    everything = [f"{keys.prefix}/**"]
    rules = [_rule("listen", LISTEN, everything), _rule("send", ALL, everything, flow="egress")]
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for i in sorted(set(robots)):
        name = robot_name(i)
        if name in revoked:
            continue
        rules += [
            _rule(f"speak-{name}", SPEAK, [keys.theta_of(i), keys.status(i)]),
            _rule(f"serve-{name}", SERVE, [keys.latest(i), keys.keyframes(i)]),
            _rule(f"token-{name}", TOKEN, [keys.alive(i)]),
        ]
        subjects.append({"id": name, "cert_common_names": [name]})
        policies.append({"id": name, "rules": [f"speak-{name}", f"serve-{name}", f"token-{name}", "listen", "send"],
                         "subjects": [name]})
    if monitor and MONITOR_NAME not in revoked:
        subjects.append({"id": MONITOR_NAME, "cert_common_names": [MONITOR_NAME]})
        policies.append({"id": MONITOR_NAME, "rules": ["listen", "send"], "subjects": [MONITOR_NAME]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}
