"""Kubernetes NetworkPolicy semantics over rendered manifests: may pod A open a connection to
port P of pod B?

The rules are the API's (networking.k8s.io/v1, "Network Policies" in the Kubernetes docs):

- a pod that no policy of a direction selects is open in that direction;
- once any policy of that direction selects it, only what some rule of those policies allows
  gets through (policies add up, none subtracts);
- a connection needs both: the source's egress and the destination's ingress allow it;
- a peer with a ``podSelector`` alone means pods of the policy's own namespace; with a
  ``namespaceSelector``, pods of the namespaces it selects; both: both must match; an empty
  selector ``{}`` selects everything; a rule without peers allows every peer;
- a rule without ports allows every port; a named port is the destination pod's container port
  of that name; the protocol defaults to TCP; ``endPort`` makes a range;
- ``policyTypes``, when absent, is Ingress, plus Egress when the policy has egress rules.

``ipBlock`` peers are refused: pods are matched by labels here, not by address.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

NAMESPACE_NAME_LABEL = "kubernetes.io/metadata.name"


@dataclass(frozen=True)
class Pod:
    """A pod as policies see it: namespace, labels, and its named container ports."""

    namespace: str
    labels: Mapping[str, str]
    ports: Mapping[str, int] = field(default_factory=dict)


def selects(selector: Mapping[str, Any], labels: Mapping[str, str]) -> bool:
    """Whether a ``LabelSelector`` (``matchLabels`` and ``matchExpressions``) selects ``labels``;
    the empty selector selects everything."""
    if any(labels.get(k) != v for k, v in selector.get("matchLabels", {}).items()):
        return False
    for expr in selector.get("matchExpressions", []):
        key, op, values = expr["key"], expr["operator"], expr.get("values", [])
        if op == "In" and labels.get(key) not in values:
            return False
        if op == "NotIn" and key in labels and labels[key] in values:
            return False
        if op == "Exists" and key not in labels:
            return False
        if op == "DoesNotExist" and key in labels:
            return False
        if op not in ("In", "NotIn", "Exists", "DoesNotExist"):
            raise ValueError(f"matchExpressions operator {op!r} is not one of In, NotIn, Exists, DoesNotExist")
    return True


class Cluster:
    """Namespaces (name -> labels) and the NetworkPolicy objects in force."""

    def __init__(self, namespaces: Mapping[str, Mapping[str, str]], objects: Iterable[Mapping[str, Any]]) -> None:
        # The API server labels every namespace with its own name.
        self.namespaces = {n: {**labels, NAMESPACE_NAME_LABEL: n} for n, labels in namespaces.items()}
        self.policies = [o for o in objects if o["kind"] == "NetworkPolicy"]
        for policy in self.policies:
            if policy["metadata"].get("namespace") not in self.namespaces:
                name = policy["metadata"]["name"]
                raise ValueError(f"NetworkPolicy {name}: its namespace is not among {sorted(self.namespaces)}")

    def allows(self, src: Pod, dst: Pod, port: int, protocol: str = "TCP") -> bool:
        """Whether ``src`` may open a connection to ``port``/``protocol`` of ``dst``."""
        return self._direction("Egress", src, dst, port, protocol) and self._direction(
            "Ingress", dst, src, port, protocol
        )

    def _direction(self, kind: str, subject: Pod, peer: Pod, port: int, protocol: str) -> bool:
        """Whether the ``kind`` policies selecting ``subject`` let it talk with ``peer``."""
        rules_key, peers_key = ("ingress", "from") if kind == "Ingress" else ("egress", "to")
        destination = subject if kind == "Ingress" else peer
        selecting = [
            p
            for p in self.policies
            if p["metadata"]["namespace"] == subject.namespace
            and kind in _policy_types(p)
            and selects(p["spec"]["podSelector"], subject.labels)
        ]
        if not selecting:
            return True
        for policy in selecting:
            for rule in policy["spec"].get(rules_key) or []:
                peers = rule.get(peers_key) or []
                if peers and not any(self._peer_matches(p, policy["metadata"]["namespace"], peer) for p in peers):
                    continue
                if _port_matches(rule.get("ports") or [], destination, port, protocol):
                    return True
        return False

    def _peer_matches(self, peer: Mapping[str, Any], policy_namespace: str, pod: Pod) -> bool:
        if "ipBlock" in peer:
            raise ValueError("ipBlock peers are not evaluated: pods are matched by labels")
        if "namespaceSelector" in peer:
            in_namespace = selects(peer["namespaceSelector"], self.namespaces[pod.namespace])
        else:
            in_namespace = pod.namespace == policy_namespace
        return in_namespace and selects(peer.get("podSelector", {}), pod.labels)


def _policy_types(policy: Mapping[str, Any]) -> list[str]:
    spec = policy["spec"]
    return spec.get("policyTypes") or ["Ingress", *(["Egress"] if "egress" in spec else [])]


def _port_matches(ports: list[Mapping[str, Any]], destination: Pod, port: int, protocol: str) -> bool:
    if not ports:
        return True
    for entry in ports:
        if entry.get("protocol", "TCP") != protocol:
            continue
        if "port" not in entry:
            return True
        first = entry["port"]
        if isinstance(first, str):
            if first not in destination.ports:
                continue
            first = destination.ports[first]
        if first <= port <= entry.get("endPort", first):
            return True
    return False
