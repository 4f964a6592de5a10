"""The network policies' intent, shown by evaluating them: for every pair of roles, whether one
may reach the other, from the rendered manifests, against the table in docs/kubernetes.md; and
the semantics the evaluator (support.network_policy) gives policies, one rule at a time."""

from __future__ import annotations

import re
from typing import Any

import kubernetes_validate
import pytest
import yaml
from support.k8s_manifests import JOBSET, K8S, ROOT, build, build_with_components, kustomize
from support.network_policy import Cluster, Pod, selects

DOCS = ROOT / "docs" / "kubernetes.md"
RAY_EGRESS = K8S / "examples" / "ray-trainer-egress.yaml"
OVERLAYS = ("gpu-cluster", "gpu-mjwarp", "dev-cpu", "jobset")
TRUSTED, ELSEWHERE, MONITORING = "rl", "elsewhere", "monitoring"
VECSIM = {"app.kubernetes.io/name": "vecsim", "app.kubernetes.io/part-of": "vecsim"}
TRAINER = {"vecsim/trainer": "true"}


def rendered(overlay: str, monitoring: bool = False) -> tuple[dict[str, Any], ...]:
    if overlay == "jobset":
        return build_with_components("jobset", ("monitoring",)) if monitoring else kustomize(JOBSET)
    return build_with_components(overlay, ("monitoring",)) if monitoring else build(overlay)


def job_namespace(objects: tuple[dict[str, Any], ...]) -> str:
    (namespace,) = [o["metadata"]["name"] for o in objects if o["kind"] == "Namespace"]
    return namespace


def pod_labels(objects: tuple[dict[str, Any], ...], component: str) -> tuple[dict[str, str], dict[str, int]]:
    """The labels and named ports of the rendered pods of ``component`` (a StatefulSet's,
    Deployment's or JobSet replicated job's pod template)."""
    templates = [o["spec"]["template"] for o in objects if o["kind"] in ("StatefulSet", "Deployment")]
    for jobset in (o for o in objects if o["kind"] == "JobSet"):
        templates += [job["template"]["spec"]["template"] for job in jobset["spec"]["replicatedJobs"]]
    (template,) = [t for t in templates if t["metadata"]["labels"].get("app.kubernetes.io/component") == component]
    ports = {p["name"]: p["containerPort"] for c in template["spec"]["containers"] for p in c.get("ports", [])}
    return template["metadata"]["labels"], ports


def roles(objects: tuple[dict[str, Any], ...]) -> dict[str, Pod]:
    """The pods the docs' table names, as the rendered manifests make vecsim's."""
    ns = job_namespace(objects)
    sim_labels, sim_ports = pod_labels(objects, "sim")
    controller_labels, controller_ports = pod_labels(objects, "controller")
    return {
        "sim": Pod(ns, sim_labels, sim_ports),
        "controller": Pod(ns, controller_labels, controller_ports),
        "trainer": Pod(ns, {**TRAINER, "app": "trainer"}, {"http": 8080}),
        "trainer in a `vecsim/trainers` namespace": Pod(TRUSTED, TRAINER),
        "trainer in another namespace": Pod(ELSEWHERE, TRAINER),
        "other pod": Pod(ns, {"app": "something-else"}, {"http": 80}),
        "kube-dns": Pod("kube-system", {"k8s-app": "kube-dns"}, {"dns": 53}),
        "Prometheus": Pod(MONITORING, {"app.kubernetes.io/name": "prometheus"}),
    }


def cluster(objects: tuple[dict[str, Any], ...], extra: tuple[dict[str, Any], ...] = ()) -> Cluster:
    namespaces = {
        job_namespace(objects): {},
        TRUSTED: {"vecsim/trainers": "true"},
        ELSEWHERE: {},
        MONITORING: {},
        "kube-system": {},
    }
    return Cluster(namespaces, [*objects, *extra])


def docs_table() -> tuple[list[tuple[str, int, str]], dict[str, list[str]]]:
    """(columns: (role, port, protocol)), {row role: cells} of the docs' "who may reach whom" table."""
    text = DOCS.read_text()
    lines = [line for line in text[text.index("| from \\ to |") :].splitlines()]
    table = [
        [cell.strip() for cell in line.strip("|").split("|")]
        for line in lines[: next(i for i, line in enumerate(lines) if not line.startswith("|"))]
    ]
    columns = []
    for head in table[0][1:]:
        name, port, protocol = re.fullmatch(r"(.+) :(\d+)(?:/(\w+))?", head).groups()
        columns.append((name, int(port), protocol or "TCP"))
    return columns, {row[0]: row[1:] for row in table[2:]}


@pytest.mark.parametrize("monitoring", [False, True], ids=["plain", "with-monitoring"])
@pytest.mark.parametrize("overlay", OVERLAYS)
def test_every_pair_of_roles_is_allowed_or_denied_as_the_docs_table_says(overlay: str, monitoring: bool) -> None:
    objects = rendered(overlay, monitoring)
    pods = roles(objects)
    net = cluster(objects)
    columns, rows = docs_table()
    assert set(rows) == set(pods), "the docs' table names other roles than the test"
    wrong = []
    for source, cells in rows.items():
        for (dest, port, protocol), cell in zip(columns, cells, strict=True):
            expected = cell == "yes" or (cell == "monitoring" and monitoring)
            assert cell in ("yes", "no", "monitoring"), f"cell {source} -> {dest}: {cell!r}"
            if net.allows(pods[source], pods[dest], port, protocol) != expected:
                wrong.append(f"{source} -> {dest} :{port}/{protocol}: docs say {cell}")
    assert wrong == []


def test_the_ray_example_lets_a_raycluster_that_denies_egress_reach_the_job() -> None:
    objects = build("gpu-cluster")
    pods = roles(objects)
    example = yaml.safe_load(RAY_EGRESS.read_text())
    kubernetes_validate.validate(example, kubernetes_validate.latest_version(), strict=True)
    ray_labels = example["spec"]["podSelector"]["matchLabels"]
    namespace = example["metadata"]["namespace"]
    # KubeRay-style: the RayCluster's pods may talk only among themselves.
    deny = {
        "apiVersion": "networking.k8s.io/v1",
        "kind": "NetworkPolicy",
        "metadata": {"name": "raycluster-deny", "namespace": namespace},
        "spec": {
            "podSelector": {"matchLabels": ray_labels},
            "policyTypes": ["Ingress", "Egress"],
            "egress": [{"to": [{"podSelector": {"matchLabels": ray_labels}}]}],
        },
    }
    ray = Pod(namespace, {**ray_labels, **TRAINER})
    namespaces = {job_namespace(objects): {}, namespace: {"vecsim/trainers": "true"}, "kube-system": {}}
    assert (
        job_namespace(objects)
        == example["spec"]["egress"][0]["to"][0]["namespaceSelector"]["matchLabels"]["kubernetes.io/metadata.name"]
    )
    denied = Cluster(namespaces, [*objects, deny])
    opened = Cluster(namespaces, [*objects, deny, example])
    for dest, port, protocol in (("sim", 8100, "TCP"), ("controller", 8000, "TCP"), ("kube-dns", 53, "UDP")):
        assert not denied.allows(ray, pods[dest], port, protocol), dest
        assert opened.allows(ray, pods[dest], port, protocol), dest
    assert not opened.allows(ray, pods["other pod"], 80)
    # Without vecsim's trainer label the sims still refuse it.
    assert not opened.allows(Pod(namespace, ray_labels), pods["sim"], 8100)


# --- the evaluator's semantics -----------------------------------------------------------------


def policy(name: str, selector: dict[str, Any], namespace: str = "a", **spec: Any) -> dict[str, Any]:
    return {
        "kind": "NetworkPolicy",
        "metadata": {"name": name, "namespace": namespace},
        "spec": {"podSelector": selector, **spec},
    }


WEB = Pod("a", {"app": "web"}, {"http": 8080})
CLIENT = Pod("a", {"app": "client"})
FAR_CLIENT = Pod("b", {"app": "client"})
NAMESPACES = {"a": {}, "b": {"team": "b"}}


def test_a_pod_no_policy_selects_is_open_both_ways() -> None:
    net = Cluster(NAMESPACES, [policy("other", {"matchLabels": {"app": "db"}}, policyTypes=["Ingress", "Egress"])])
    assert net.allows(CLIENT, WEB, 8080) and net.allows(WEB, CLIENT, 1234)


def test_a_selecting_policy_without_rules_denies_its_direction_only() -> None:
    net = Cluster(NAMESPACES, [policy("deny-in", {"matchLabels": {"app": "web"}})])
    assert not net.allows(CLIENT, WEB, 8080)
    assert net.allows(WEB, CLIENT, 1234)  # policyTypes defaults to Ingress alone


def test_policies_add_up() -> None:
    allow = {"ingress": [{"from": [{"podSelector": {"matchLabels": {"app": "client"}}}]}]}
    net = Cluster(NAMESPACES, [policy("deny-in", {}), policy("allow-client", {"matchLabels": {"app": "web"}}, **allow)])
    assert net.allows(CLIENT, WEB, 8080)
    assert not net.allows(WEB, CLIENT, 80)


def test_a_pod_selector_alone_means_the_policys_namespace() -> None:
    rule = {"ingress": [{"from": [{"podSelector": {"matchLabels": {"app": "client"}}}]}]}
    net = Cluster(NAMESPACES, [policy("p", {"matchLabels": {"app": "web"}}, **rule)])
    assert net.allows(CLIENT, WEB, 8080) and not net.allows(FAR_CLIENT, WEB, 8080)


def test_namespace_and_pod_selectors_in_one_peer_must_both_match() -> None:
    both = {"namespaceSelector": {"matchLabels": {"team": "b"}}, "podSelector": {"matchLabels": {"app": "client"}}}
    net = Cluster(NAMESPACES, [policy("p", {"matchLabels": {"app": "web"}}, ingress=[{"from": [both]}])])
    assert net.allows(FAR_CLIENT, WEB, 8080)
    assert not net.allows(Pod("b", {"app": "other"}), WEB, 8080)
    assert not net.allows(CLIENT, WEB, 8080)


def test_named_ports_are_the_destinations_and_protocol_defaults_to_tcp() -> None:
    rule = {"ingress": [{"ports": [{"port": "http"}]}]}
    net = Cluster(NAMESPACES, [policy("p", {"matchLabels": {"app": "web"}}, **rule)])
    assert net.allows(CLIENT, WEB, 8080)
    assert not net.allows(CLIENT, WEB, 8081) and not net.allows(CLIENT, WEB, 8080, "UDP")


def test_end_port_makes_a_range() -> None:
    rule = {"egress": [{"ports": [{"port": 8000, "endPort": 8100}]}]}
    net = Cluster(NAMESPACES, [policy("p", {"matchLabels": {"app": "client"}}, **rule)])
    assert net.allows(CLIENT, WEB, 8050) and not net.allows(CLIENT, WEB, 8101)


def test_match_expressions_select_as_the_api_does() -> None:
    selector = {
        "matchExpressions": [
            {"key": "app", "operator": "In", "values": ["web"]},
            {"key": "canary", "operator": "DoesNotExist"},
        ]
    }
    assert selects(selector, {"app": "web"}) and not selects(selector, {"app": "web", "canary": "1"})
    assert selects({}, {"anything": "x"})
    with pytest.raises(ValueError, match="operator"):
        selects({"matchExpressions": [{"key": "app", "operator": "Like"}]}, {})


def test_ip_block_peers_are_refused_not_guessed() -> None:
    net = Cluster(NAMESPACES, [policy("p", {}, ingress=[{"from": [{"ipBlock": {"cidr": "10.0.0.0/8"}}]}])])
    with pytest.raises(ValueError, match="ipBlock"):
        net.allows(CLIENT, WEB, 8080)
