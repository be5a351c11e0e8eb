"""Zenoh TLS and access control (ACL) from the ``bus`` config section, for stations on several hosts.

The models mirror zenoh 1.x's own config (``transport/link/tls`` and ``access_control``), so a lab can
read zenoh's documentation for their meaning; ``zenoh_security_json5`` translates them into the
keys that ``orchestrator.bus.zenoh_config`` inserts. Nothing here opens a session.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from pydantic import Field, model_validator

from drivers.config import StrictModel

AclMessage = Literal[
    "put", "delete", "declare_subscriber", "query", "declare_queryable", "reply",
    "liveliness_token", "declare_liveliness_subscriber", "liveliness_query",
]


class BusTlsConfig(StrictModel):
    """TLS for ``tls/HOST:PORT`` endpoints: this host's certificate and key, and the CA that signs the others.

    A listener presents ``certificate`` + ``private_key``; a connector checks the listener against
    ``root_ca_certificate``. ``mutual`` (mTLS) makes listeners check connectors too, so every host
    needs all three files, and ACL subjects can then match certificate common names.
    """

    root_ca_certificate: Path | None = Field(None, description="PEM CA certificate that signed the other hosts'")
    certificate: Path | None = Field(None, description="PEM certificate of this host (listening; mTLS connecting)")
    private_key: Path | None = Field(None, description="PEM private key of this host's certificate")
    mutual: bool = Field(False, description="mTLS: listeners also verify the connectors' certificates")
    verify_name_on_connect: bool = Field(True, description="check that the listener's certificate names its host")

    @model_validator(mode="after")
    def _files(self) -> BusTlsConfig:
        if (self.certificate is None) != (self.private_key is None):
            raise ValueError("tls.certificate and tls.private_key go together (set both or neither)")
        if self.mutual and None in (self.root_ca_certificate, self.certificate, self.private_key):
            raise ValueError("tls.mutual needs root_ca_certificate, certificate and private_key")
        for name in ("root_ca_certificate", "certificate", "private_key"):
            path = getattr(self, name)
            if path is not None and not Path(path).is_file():
                raise ValueError(f"tls.{name}: no such file {str(path)!r}")
        return self


class AclRule(StrictModel):
    """Allow or deny some message kinds on some key expressions (zenoh ``access_control.rules[]``)."""

    id: str = Field(min_length=1)
    permission: Literal["allow", "deny"]
    messages: list[AclMessage] = Field(min_length=1)
    key_exprs: list[str] = Field(min_length=1, description="full zenoh key expressions, e.g. trackdeform/**")
    flows: list[Literal["ingress", "egress"]] = Field(default=["ingress", "egress"])


class AclSubject(StrictModel):
    """Who a rule applies to: remote hosts by network interface, TLS certificate common name or username."""

    id: str = Field(min_length=1)
    interfaces: list[str] | None = Field(None, description="local network interfaces the remote comes in on")
    cert_common_names: list[str] | None = Field(None, description="CN of the remote's certificate (mTLS)")
    usernames: list[str] | None = None

    @model_validator(mode="after")
    def _some_match(self) -> AclSubject:
        if not (self.interfaces or self.cert_common_names or self.usernames):
            raise ValueError(f"subject {self.id!r} matches nobody: give interfaces, cert_common_names or usernames")
        return self


class AclPolicy(StrictModel):
    """Rules applied to subjects (zenoh ``access_control.policies[]``)."""

    rules: list[str] = Field(min_length=1)
    subjects: list[str] = Field(min_length=1)


class BusAclConfig(StrictModel):
    """Zenoh access control: messages not matched by a policy get ``default_permission``."""

    enabled: bool = True
    default_permission: Literal["allow", "deny"] = "deny"
    rules: list[AclRule] = Field(default=[])
    subjects: list[AclSubject] = Field(default=[])
    policies: list[AclPolicy] = Field(default=[])

    @model_validator(mode="after")
    def _references(self) -> BusAclConfig:
        rules, subjects = {r.id for r in self.rules}, {s.id for s in self.subjects}
        for i, p in enumerate(self.policies):
            for kind, names, known in (("rule", p.rules, rules), ("subject", p.subjects, subjects)):
                unknown = sorted(set(names) - known)
                if unknown:
                    raise ValueError(f"policies[{i}] names unknown {kind}(s) {unknown}; defined: {sorted(known)}")
        return self


def check_endpoints(tls: BusTlsConfig | None, listen: list[str], connect: list[str]) -> None:
    """Raise ValueError when ``tls/`` endpoints lack the files TLS needs on that side."""
    if any(e.startswith("tls/") for e in listen) and (tls is None or tls.certificate is None):
        raise ValueError("a tls/ listen endpoint needs bus.tls.certificate and bus.tls.private_key")
    if any(e.startswith("tls/") for e in connect) and (tls is None or tls.root_ca_certificate is None):
        raise ValueError("a tls/ connect endpoint needs bus.tls.root_ca_certificate to verify the listener")


def zenoh_security_json5(tls: BusTlsConfig | None, acl: BusAclConfig | None) -> dict[str, Any]:
    """``{zenoh config key: JSON value}`` for TLS and ACL; empty when neither is configured."""
    out: dict[str, Any] = {}
    if tls is not None:
        ca = None if tls.root_ca_certificate is None else str(tls.root_ca_certificate)
        cert = None if tls.certificate is None else str(tls.certificate)
        key = None if tls.private_key is None else str(tls.private_key)
        out["transport/link/tls/root_ca_certificate"] = ca
        out["transport/link/tls/listen_certificate"] = cert
        out["transport/link/tls/listen_private_key"] = key
        out["transport/link/tls/enable_mtls"] = tls.mutual
        out["transport/link/tls/verify_name_on_connect"] = tls.verify_name_on_connect
        if tls.mutual:
            out["transport/link/tls/connect_certificate"] = cert
            out["transport/link/tls/connect_private_key"] = key
    if acl is not None:
        out["access_control"] = {
            "enabled": acl.enabled,
            "default_permission": acl.default_permission,
            "rules": [r.model_dump() for r in acl.rules],
            "subjects": [s.model_dump(exclude_none=True) for s in acl.subjects],
            "policies": [p.model_dump() for p in acl.policies],
        }
    return out
