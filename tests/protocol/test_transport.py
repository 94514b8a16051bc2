"""TransportConfig -> Zenoh config mapping, validation, and one session's own behaviour."""

from __future__ import annotations

import json

import pytest

from protocol.transport import TransportConfig
from tests.protocol.helpers import free_port


def test_defaults_map_onto_zenoh_keys():
    cfg = TransportConfig(listen=["tcp/127.0.0.1:7447"], connect=["tcp/127.0.0.1:7448"])
    s = cfg.zenoh_settings()
    assert json.loads(s["mode"]) == "peer"
    assert json.loads(s["listen/endpoints"]) == ["tcp/127.0.0.1:7447"]
    assert json.loads(s["connect/endpoints"]) == ["tcp/127.0.0.1:7448"]
    assert json.loads(s["scouting/multicast/enabled"]) is False
    assert json.loads(s["transport/link/tx/lease"]) == 2000
    # Zenoh counts wait_before_close in microseconds; by default it is half the lease
    assert json.loads(s["transport/link/tx/queue/congestion_control/block/wait_before_close"]) == 1_000_000
    conf = cfg.to_zenoh()  # Zenoh accepts every entry
    assert json.loads(conf.get_json("transport/link/tx/lease")) == 2000
    assert json.loads(conf.get_json("transport/link/rx/max_message_size")) == cfg.max_message_bytes
    assert not any(k.startswith("transport/link/tls") for k in s)


def test_tls_settings_and_extra_overrides(tmp_path):
    paths = {}
    for name in ("ca", "cert", "key"):
        paths[name] = tmp_path / f"{name}.pem"
        paths[name].write_text("placeholder")
    cfg = TransportConfig(listen=["tls/127.0.0.1:7447"], tls_root_ca=str(paths["ca"]), tls_cert=str(paths["cert"]),
                          tls_key=str(paths["key"]), enable_mtls=True,
                          extra={"transport/link/tx/queue/size/data": "4"})
    s = cfg.zenoh_settings()
    tls = "transport/link/tls/"
    assert json.loads(s[tls + "root_ca_certificate"]) == str(paths["ca"])
    for role in ("listen", "connect"):
        assert json.loads(s[tls + f"{role}_certificate"]) == str(paths["cert"])
        assert json.loads(s[tls + f"{role}_private_key"]) == str(paths["key"])
    assert json.loads(s[tls + "enable_mtls"]) is True
    assert s["transport/link/tx/queue/size/data"] == "4"
    conf = cfg.to_zenoh()
    assert json.loads(conf.get_json(tls + "enable_mtls")) is True
    assert json.loads(conf.get_json("transport/link/tx/queue/size/data")) == 4


@pytest.mark.parametrize("kw,match", [
    (dict(listen=["127.0.0.1:7447"]), "endpoints like"),
    (dict(listen=[], connect=[]), "never meet a peer"),
    (dict(lease_ms=10), "lease_ms"),
    (dict(block_wait_before_close_ms=0), "block_wait_before_close_ms"),
    (dict(block_wait_before_close_ms=2000, lease_ms=2000), "below lease_ms"),
    (dict(tls_root_ca="/nonexistent/ca.pem"), "no such file"),
    (dict(listen=["tls/127.0.0.1:7447"]), "tls_root_ca"),
    (dict(enable_mtls=True), "mutual TLS .*needs tls_root_ca"),
    (dict(access_control={"enabled": True}), "needs tls/ endpoints and mutual TLS"),
    (dict(extra={"mode": 3}), "json5 strings"),
])
def test_bad_configs_say_why(kw, match):
    with pytest.raises(ValueError, match=match):
        TransportConfig(**kw).validate()


def test_bad_extra_override_is_a_clear_error():
    with pytest.raises(ValueError, match="Zenoh refuses"):
        TransportConfig(extra={"transport/link/tx/lease": '"soon"'}).to_zenoh()


def test_callback_errors_are_contained_and_close_is_idempotent(peers):
    got = peers("self-check", "--listen", str(free_port())).expect("checked", 30)
    assert got["delivered"] is True
    assert got["callback_errors"] == 1  # the raising callback, counted, not propagated
    assert got["served"] == "newest" and got["missing"] is None
    # latest_since: served only once that round is reached; a malformed parameter counts as absent
    assert got["served_since"] == ["newest", None]
    assert got["bad_parameter"] == "newest"
    # held: the deltas since the asker's base, in order; a base not in the chain gets the full one
    assert got["from_held"] == [["d4", "d5"], ["d5"], ["newest" * 4]]
    assert "closed" in got["after_close"]
    assert got["stats"]["bytes_out"]["theta"] == 10 and got["stats"]["bytes_out"]["latest"] == 3 * 6 + 2 * 3 + 24


def test_concurrent_puts_never_lose_their_publisher(peers):
    # Snapshots go to every neighbour at once, each on a key of its own: with more neighbours
    # than the publisher cache, one put undeclared another's publisher mid-flight.
    got = peers("publish-many", "--listen", str(free_port())).expect("published", 60)
    assert got["failed"] == 0, got["failures"]
    assert got["received"] == got["sent"]
    assert got["publishers_kept"] <= 4  # idle ones are still evicted
