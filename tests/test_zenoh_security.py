"""Zenoh TLS and access control from the bus config, on loopback with certificates the test makes (openssl)."""

from __future__ import annotations

import json
import shutil
import subprocess
import time
from pathlib import Path

import pytest
from pydantic import ValidationError

from orchestrator.bus import Bus, zenoh_config
from orchestrator.cli_router import router_config
from orchestrator.config import BusConfig
from orchestrator.zenoh_security import BusAclConfig, BusTlsConfig, zenoh_security_json5

needs_openssl = pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl CLI not installed")


def _openssl(*args: str) -> None:
    subprocess.run(["openssl", *args], check=True, capture_output=True)


def _ca(d: Path, name: str) -> tuple[Path, Path]:
    key, crt = d / f"{name}.key", d / f"{name}.crt"
    _openssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2", "-subj", f"/CN={name}",
             "-keyout", str(key), "-out", str(crt))
    return crt, key


def _cert(d: Path, ca: tuple[Path, Path], cn: str) -> tuple[Path, Path]:
    """A certificate for CN ``cn`` valid for 127.0.0.1 (server and client use), signed by ``ca``."""
    key, csr, crt, ext = d / f"{cn}.key", d / f"{cn}.csr", d / f"{cn}.crt", d / f"{cn}.ext"
    ext.write_text("subjectAltName=IP:127.0.0.1\nextendedKeyUsage=serverAuth,clientAuth\n")
    _openssl("req", "-newkey", "rsa:2048", "-nodes", "-subj", f"/CN={cn}", "-keyout", str(key), "-out", str(csr))
    _openssl("x509", "-req", "-in", str(csr), "-CA", str(ca[0]), "-CAkey", str(ca[1]), "-CAcreateserial",
             "-days", "2", "-extfile", str(ext), "-out", str(crt))
    return crt, key


def _received(bus: Bus, sub: object, publishers: list[tuple[Bus, bytes]], key: str, seconds: float = 4.0) -> set:
    """Payloads ``sub`` got while each publisher put its payload on ``key`` every 50 ms for ``seconds``."""
    got: set[bytes] = set()
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        for pub, payload in publishers:
            pub.put(key, payload)
        time.sleep(0.05)
        while (s := sub.try_recv()) is not None:  # type: ignore[attr-defined]
            got.add(s.payload.to_bytes())
    return got


def test_security_keys_are_zenohs_own(tmp_path: Path) -> None:
    """Every translated key and value is accepted by zenoh's config (unknown keys would raise)."""
    for f in ("ca.crt", "me.crt", "me.key"):
        (tmp_path / f).write_text("x")
    tls = BusTlsConfig(root_ca_certificate=tmp_path / "ca.crt", certificate=tmp_path / "me.crt",
                       private_key=tmp_path / "me.key", mutual=True)
    acl = BusAclConfig.model_validate({
        "rules": [{"id": "pub", "permission": "allow", "messages": ["put"], "key_exprs": ["trackdeform/**"]}],
        "subjects": [{"id": "daemon", "cert_common_names": ["daemon"]}],
        "policies": [{"rules": ["pub"], "subjects": ["daemon"]}],
    })
    bus = BusConfig(listen=["tls/127.0.0.1:7447"], tls=tls, access_control=acl)
    c = zenoh_config(bus)
    got = json.loads(c.get_json("transport/link/tls"))
    assert got["listen_certificate"] == str(tmp_path / "me.crt") and got["enable_mtls"] is True
    assert got["connect_private_key"] == str(tmp_path / "me.key")
    assert json.loads(c.get_json("access_control"))["policies"][0]["subjects"] == ["daemon"]
    assert zenoh_security_json5(None, None) == {}


def test_bad_security_config_names_the_field(tmp_path: Path) -> None:
    with pytest.raises(ValidationError, match="tls/ listen endpoint needs bus.tls.certificate"):
        BusConfig(listen=["tls/127.0.0.1:7447"])
    with pytest.raises(ValidationError, match="tls/ connect endpoint needs bus.tls.root_ca_certificate"):
        BusConfig(listen=[], connect=["tls/127.0.0.1:7447"])
    with pytest.raises(ValidationError, match="no such file"):
        BusTlsConfig(root_ca_certificate=tmp_path / "missing.crt")
    with pytest.raises(ValidationError, match="go together"):
        (tmp_path / "a.crt").write_text("x")
        BusTlsConfig(certificate=tmp_path / "a.crt")
    with pytest.raises(ValidationError, match=r"unknown rule\(s\) \['nope'\]"):
        BusAclConfig.model_validate({"subjects": [{"id": "s", "interfaces": ["lo"]}],
                                     "policies": [{"rules": ["nope"], "subjects": ["s"]}]})
    with pytest.raises(ValidationError, match="matches nobody"):
        BusAclConfig.model_validate({"subjects": [{"id": "s"}]})


@needs_openssl
def test_tls_loopback_only_trusted_certificates_connect(tmp_path: Path, port: int) -> None:
    """A listener on tls/127.0.0.1: a connector trusting its CA gets the data; one trusting another CA cannot open."""
    ca = _ca(tmp_path, "ca")
    server = _cert(tmp_path, ca, "daemon")
    other_ca = _ca(tmp_path, "other")
    endpoint = f"tls/127.0.0.1:{port}"
    listen_cfg = BusConfig(listen=[endpoint], tls=BusTlsConfig(certificate=server[0], private_key=server[1]))
    good = BusConfig(listen=[], connect=[endpoint], tls=BusTlsConfig(root_ca_certificate=ca[0]))
    bad = BusConfig(mode="client", listen=[], connect=[endpoint], tls=BusTlsConfig(root_ca_certificate=other_ca[0]))
    plain = BusConfig(mode="client", listen=[], connect=[f"tcp/127.0.0.1:{port}"])
    with Bus(listen_cfg, "t") as daemon, Bus(good, "t", listen=False) as watcher:
        key = daemon.key("keypoints")
        sub = watcher.subscribe(key, ring=16)
        assert _received(watcher, sub, [(daemon, b"kp")], key) == {b"kp"}
        for cfg in (bad, plain):  # a client that cannot reach its router fails to open
            with pytest.raises(RuntimeError, match="cannot open the zenoh session"):
                Bus(cfg, "t", listen=False).close()


@needs_openssl
def test_router_acl_by_certificate_name(tmp_path: Path, port: int) -> None:
    """mTLS router, default deny: the daemon's CN may put, the watcher's may subscribe, an intruder's put is dropped."""
    import zenoh

    ca = _ca(tmp_path, "ca")
    certs = {cn: _cert(tmp_path, ca, cn) for cn in ("router", "daemon", "watcher", "intruder")}
    endpoint = f"tls/127.0.0.1:{port}"

    def tls(cn: str) -> BusTlsConfig:
        return BusTlsConfig(root_ca_certificate=ca[0], certificate=certs[cn][0], private_key=certs[cn][1], mutual=True)

    acl = BusAclConfig.model_validate({
        "default_permission": "deny",
        "rules": [
            # the daemon puts (ingress) and learns of the subscribers (egress declarations) it puts for
            {"id": "publish", "permission": "allow", "messages": ["put", "declare_subscriber"],
             "key_exprs": ["trackdeform/**"]},
            # the watcher declares its subscriber (ingress) and is sent the puts (egress), but cannot put
            {"id": "subscribe", "permission": "allow", "messages": ["declare_subscriber"], "flows": ["ingress"],
             "key_exprs": ["trackdeform/**"]},
            {"id": "receive", "permission": "allow", "messages": ["put"], "flows": ["egress"],
             "key_exprs": ["trackdeform/**"]},
        ],
        "subjects": [{"id": "daemon", "cert_common_names": ["daemon"]},
                     {"id": "watcher", "cert_common_names": ["watcher"]}],
        "policies": [{"rules": ["publish"], "subjects": ["daemon"]},
                     {"rules": ["subscribe", "receive"], "subjects": ["watcher"]}],
    })
    router_bus = BusConfig(listen=[endpoint], tls=tls("router"), access_control=acl)
    router = zenoh.open(router_config(router_bus, [endpoint], []))
    try:
        def client(cn: str) -> Bus:
            return Bus(BusConfig(mode="client", listen=[], connect=[endpoint], tls=tls(cn)), "t", listen=False)

        with client("daemon") as daemon, client("watcher") as watcher, client("intruder") as intruder:
            key = daemon.key("keypoints")
            sub = watcher.subscribe(key, ring=64)
            got = _received(watcher, sub, [(daemon, b"daemon"), (intruder, b"intruder")], key)
            assert got == {b"daemon"}
            own = daemon.subscribe(key, ring=64)  # the watcher's own puts never leave it through the router
            assert _received(daemon, own, [(watcher, b"watcher"), (daemon, b"daemon")], key) == {b"daemon"}
    finally:
        router.close()
