"""The fleet's manifests: the JobSet overlay (trainer, controller and sims as one unit, admitted by
Kueue), the network policies, the monitoring and autoscaling components, and topology spread.

Core objects pass ``kubernetes-validate --strict``, a JobSet's Job templates included. The other
projects' objects pass those projects' published types, installed from PyPI at named versions
(docs/kubernetes.md, "How the manifests are tested"): a field those types do not know, a value
outside their patterns or a wrong type fails.
"""

from __future__ import annotations

import copy
import re
from pathlib import Path
from typing import Any

import kubernetes_validate
import pydantic
import pytest
import yaml
from cloudcoil.models.keda import v1alpha1 as keda_v1alpha1
from cloudcoil.models.prometheus_operator import v1 as monitoring_v1
from kubeflow_trainer_api.models.jobset_v1alpha2_job_set import JobsetV1alpha2JobSet
from support.k8s_manifests import JOBSET, ROOT, TARGETS, build, build_with_components, kustomize

from vecsim.config import load_job_config

KUBERNETES_VERSIONS = ("1.30.0", kubernetes_validate.latest_version())
LABEL_COMPONENT = "app.kubernetes.io/component"
TRAINER_LABEL = "vecsim/trainer"
KUEUE_QUEUE_LABEL = "kueue.x-k8s.io/queue-name"
MONITORED = ("monitoring", "autoscaling")


def jobset_objects() -> tuple[dict[str, Any], ...]:
    return kustomize(JOBSET)


def monitored_objects() -> tuple[dict[str, Any], ...]:
    return build_with_components("gpu-cluster", MONITORED)


def of_kind(objects: tuple[dict[str, Any], ...], kind: str) -> list[dict[str, Any]]:
    return [o for o in objects if o["kind"] == kind]


def the_jobset(objects: tuple[dict[str, Any], ...]) -> dict[str, Any]:
    (jobset,) = of_kind(objects, "JobSet")
    return jobset


def replicated_job(jobset: dict[str, Any], name: str) -> dict[str, Any]:
    return next(r for r in jobset["spec"]["replicatedJobs"] if r["name"] == name)


def pod_template(jobset: dict[str, Any], name: str) -> dict[str, Any]:
    return replicated_job(jobset, name)["template"]["spec"]["template"]


def container(template: dict[str, Any], name: str) -> dict[str, Any]:
    return next(c for c in template["spec"]["containers"] if c["name"] == name)


# --- the other projects' published types ---------------------------------------------------------


def _round_trip_jobset(obj: dict[str, Any]) -> dict[str, Any]:
    return JobsetV1alpha2JobSet.from_dict(obj).to_dict()


def _round_trip(model: type[pydantic.BaseModel]) -> Any:
    return lambda obj: model.model_validate(obj).model_dump(by_alias=True, exclude_unset=True, mode="json")


# (apiVersion, kind) -> parse with the project's type and write back what it understood.
PUBLISHED_TYPES = {
    ("jobset.x-k8s.io/v1alpha2", "JobSet"): _round_trip_jobset,
    ("monitoring.coreos.com/v1", "PodMonitor"): _round_trip(monitoring_v1.PodMonitor),
    ("monitoring.coreos.com/v1", "PrometheusRule"): _round_trip(monitoring_v1.PrometheusRule),
    ("keda.sh/v1alpha1", "ScaledObject"): _round_trip(keda_v1alpha1.ScaledObject),
}


def lost_fields(given: Any, understood: Any, path: str = "") -> list[str]:
    """Paths of ``given`` that ``understood`` lacks or holds otherwise; what ``understood``
    adds (defaults) is not a loss."""
    if isinstance(given, dict) and isinstance(understood, dict):
        return [
            p
            for k, v in given.items()
            for p in (lost_fields(v, understood[k], f"{path}/{k}") if k in understood else [f"{path}/{k}"])
        ]
    if isinstance(given, list) and isinstance(understood, list) and len(given) == len(understood):
        return [p for i, (a, b) in enumerate(zip(given, understood)) for p in lost_fields(a, b, f"{path}/{i}")]
    return [] if given == understood else [path or "/"]


def published_type_problems(obj: dict[str, Any]) -> list[str]:
    """What the object's own project's published type refuses or does not know in it."""
    round_trip = PUBLISHED_TYPES[(obj["apiVersion"], obj["kind"])]
    try:
        understood = round_trip(copy.deepcopy(obj))
    except (pydantic.ValidationError, ValueError) as exc:
        return [str(exc)]
    return [f"{path}: unknown to the published type" for path in lost_fields(obj, understood)]


def core_objects(objects: tuple[dict[str, Any], ...]) -> list[dict[str, Any]]:
    """The objects of Kubernetes' own API, plus a Job object for each JobSet replicated job's
    template (what the JobSet controller creates from it)."""
    core = [o for o in objects if (o["apiVersion"], o["kind"]) not in PUBLISHED_TYPES]
    for jobset in of_kind(objects, "JobSet"):
        for job in jobset["spec"]["replicatedJobs"]:
            name, namespace = f"{jobset['metadata']['name']}-{job['name']}-0", jobset["metadata"]["namespace"]
            meta = {"name": name, "namespace": namespace}
            core.append({"apiVersion": "batch/v1", "kind": "Job", "metadata": meta, "spec": job["template"]["spec"]})
    return core


RENDERINGS = {
    "jobset": jobset_objects,
    "gpu-cluster+monitoring+autoscaling": monitored_objects,
    "dev-cpu+monitoring": lambda: build_with_components("dev-cpu", ("monitoring",)),
    "jobset+monitoring": lambda: build_with_components("jobset", ("monitoring",)),
}


@pytest.mark.parametrize("version", KUBERNETES_VERSIONS)
@pytest.mark.parametrize("rendering", RENDERINGS)
def test_core_objects_pass_strict_schema_validation(rendering: str, version: str) -> None:
    for obj in core_objects(RENDERINGS[rendering]()):
        try:
            kubernetes_validate.validate(obj, version, strict=True)
        except kubernetes_validate.ValidationError as exc:
            pytest.fail(f"{obj['kind']}/{obj['metadata']['name']}: {exc.message} at {list(exc.path)}")


@pytest.mark.parametrize("rendering", RENDERINGS)
def test_other_projects_objects_pass_their_published_types(rendering: str) -> None:
    objects = RENDERINGS[rendering]()
    foreign = [o for o in objects if (o["apiVersion"], o["kind"]) in PUBLISHED_TYPES]
    assert foreign, f"{rendering} renders no JobSet, monitoring or KEDA object"
    for obj in foreign:
        assert published_type_problems(obj) == [], f"{obj['kind']}/{obj['metadata']['name']}"


@pytest.mark.parametrize(
    ("kind", "path", "value"),
    [
        ("JobSet", ("spec", "sucessPolicy"), {"operator": "All"}),
        ("JobSet", ("spec", "replicatedJobs", 0, "replicas"), "1"),
        ("PodMonitor", ("spec", "podMetricsEndpoints", 0, "interval"), "every 15 seconds"),
        ("PrometheusRule", ("spec", "groups", 0, "rules", 0, "for"), "a while"),
        ("PrometheusRule", ("spec", "groups", 0, "rulez"), []),
        ("ScaledObject", ("spec", "minReplicaCount"), "ten"),
        ("ScaledObject", ("spec", "scaleTargetRef", "nam"), "sim"),
    ],
)
def test_the_published_types_refuse_what_their_projects_refuse(kind: str, path: tuple[Any, ...], value: Any) -> None:
    # The check is not vacuous: a misspelt field or a wrong value fails it.
    objects = jobset_objects() + monitored_objects()
    obj = copy.deepcopy(of_kind(objects, kind)[0])
    target = obj
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = value
    assert published_type_problems(obj) != []


# --- the JobSet overlay ------------------------------------------------------------------------


def test_jobset_runs_trainer_controller_and_sims_as_one_jobset() -> None:
    objects = jobset_objects()
    jobset = the_jobset(objects)
    assert [r["name"] for r in jobset["spec"]["replicatedJobs"]] == ["trainer", "controller", "sim"]
    assert not of_kind(objects, "StatefulSet") and not of_kind(objects, "Deployment")
    for name in ("trainer", "controller", "sim"):
        assert pod_template(jobset, name)["metadata"]["labels"][LABEL_COMPONENT] == name


def test_jobset_ends_when_the_trainers_job_succeeds() -> None:
    policy = the_jobset(jobset_objects())["spec"]["successPolicy"]
    assert policy == {"operator": "All", "targetReplicatedJobs": ["trainer"]}


def test_kueue_admits_the_jobset_through_its_queue_label() -> None:
    jobset = the_jobset(jobset_objects())
    assert jobset["metadata"]["labels"][KUEUE_QUEUE_LABEL]
    # Kueue admits the whole set as one workload; a suspended-by-hand JobSet would never start.
    assert not jobset["spec"].get("suspend", False)


def test_trainer_image_and_command_are_named_only_in_trainer_yaml() -> None:
    trainer = container(pod_template(the_jobset(jobset_objects()), "trainer"), "trainer")
    ops = yaml.safe_load((JOBSET / "trainer.yaml").read_text())
    replaced = {op["path"].rsplit("/", 1)[1]: op["value"] for op in ops if op["op"] == "replace"}
    assert replaced == {"image": trainer["image"], "command": trainer["command"]}
    for path in JOBSET.iterdir():
        if path.name != "trainer.yaml":
            assert trainer["image"] not in path.read_text(), path.name


def test_jobset_sims_are_named_and_addressed_by_their_index() -> None:
    objects = jobset_objects()
    jobset = the_jobset(objects)
    template = pod_template(jobset, "sim")
    env = container(template, "sim")["env"]
    namespace = jobset["metadata"]["namespace"]
    resolved = expand_env(
        env,
        {
            "metadata.annotations['batch.kubernetes.io/job-completion-index']": "3",
            "metadata.namespace": namespace,
            "status.podIP": "10.1.2.3",
        },
    )
    from service.pod.settings import PodSettings

    settings = PodSettings.from_env(resolved)
    assert settings.name == "sim-3"
    # JobSet's pod hostname <jobset>-<replicated job>-<job index>-<pod index> under its subdomain.
    subdomain = jobset["spec"]["network"]["subdomain"]
    assert jobset["spec"]["network"]["enableDNSHostnames"] is True
    host = f"{jobset['metadata']['name']}-sim-0-3.{subdomain}.{namespace}.svc.cluster.local"
    assert settings.url == f"http://{host}:8100"
    (service,) = [s for s in of_kind(objects, "Service") if s["metadata"]["name"] == "controller"]
    port = service["spec"]["ports"][0]["port"]
    assert settings.controller_url == f"http://controller.{namespace}.svc.cluster.local:{port}"


def expand_env(env: list[dict[str, Any]], downward: dict[str, str]) -> dict[str, str]:
    """Container env as the kubelet resolves it (``$(VAR)`` of variables defined before)."""
    resolved: dict[str, str] = {}
    for var in env:
        if "value" in var:
            resolved[var["name"]] = re.sub(r"\$\((\w+)\)", lambda m: resolved.get(m.group(1), m.group(0)), var["value"])
        elif "fieldRef" in var.get("valueFrom", {}):
            resolved[var["name"]] = downward[var["valueFrom"]["fieldRef"]["fieldPath"]]
    return resolved


def test_jobset_runs_as_many_sims_as_its_job_plans(tmp_path: Path) -> None:
    objects = jobset_objects()
    jobset = the_jobset(objects)
    args = container(pod_template(jobset, "controller"), "controller")["args"]
    name = Path(args[args.index("--config") + 1]).name
    (configmap,) = of_kind(objects, "ConfigMap")
    config = tmp_path / name
    config.write_text(configmap["data"][name])
    job = load_job_config(config).job
    spec = replicated_job(jobset, "sim")["template"]["spec"]
    assert spec["completionMode"] == "Indexed"
    assert spec["completions"] == spec["parallelism"] == job.num_stages * job.pods_per_stage
    # The controller mounts the generated ConfigMap under its hashed name.
    volumes = pod_template(jobset, "controller")["spec"]["volumes"]
    assert [v["configMap"]["name"] for v in volumes if "configMap" in v] == [configmap["metadata"]["name"]]


def test_jobset_pods_follow_the_probes_and_lockdown_of_the_base() -> None:
    from service import probes

    jobset = the_jobset(jobset_objects())
    for name, want in (("sim", probes.POD), ("controller", probes.CONTROLLER)):
        c = container(pod_template(jobset, name), name)
        for kind in ("startup", "readiness", "liveness"):
            probe, expected = c[f"{kind}Probe"], getattr(want, kind)
            assert (probe["httpGet"]["path"], probe["periodSeconds"], probe["failureThreshold"]) == (
                expected.path,
                expected.period_s,
                expected.failure_threshold,
            ), f"{name} {kind}"
    for name in ("trainer", "controller", "sim"):
        spec = pod_template(jobset, name)["spec"]
        (c,) = spec["containers"]
        assert spec["securityContext"]["runAsNonRoot"] is True and spec["automountServiceAccountToken"] is False
        locked = c["securityContext"]
        assert locked["readOnlyRootFilesystem"] is True and locked["capabilities"]["drop"] == ["ALL"], name
        token = next(v for v in c["env"] if v["name"] == "VECSIM_TOKEN")["valueFrom"]["secretKeyRef"]
        assert (token["name"], token["key"], token["optional"]) == ("vecsim-token", "token", True), name


# --- spread and placement ----------------------------------------------------------------------


def sim_pod_templates() -> dict[str, dict[str, Any]]:
    templates = {t: next(o for o in build(t) if o["kind"] == "StatefulSet")["spec"]["template"] for t in TARGETS}
    templates["jobset"] = pod_template(the_jobset(jobset_objects()), "sim")
    return templates


@pytest.mark.parametrize("target", [*TARGETS, "jobset"])
def test_sim_pods_spread_across_nodes(target: str) -> None:
    template = sim_pod_templates()[target]
    from support.network_policy import selects

    by_key = {c["topologyKey"]: c for c in template["spec"]["topologySpreadConstraints"]}
    node = by_key["kubernetes.io/hostname"]
    assert (node["maxSkew"], node["whenUnsatisfiable"]) == (1, "DoNotSchedule")
    assert selects(node["labelSelector"], template["metadata"]["labels"])
    assert "topology.kubernetes.io/zone" in by_key


# --- monitoring and autoscaling ----------------------------------------------------------------


def test_podmonitor_scrapes_sims_and_the_controller_on_their_metrics_port() -> None:
    from support.network_policy import selects

    objects = monitored_objects()
    (monitor,) = of_kind(objects, "PodMonitor")
    workloads = {
        o["spec"]["template"]["metadata"]["labels"][LABEL_COMPONENT]: o
        for o in objects
        if o["kind"] in ("StatefulSet", "Deployment")
    }
    (endpoint,) = monitor["spec"]["podMetricsEndpoints"]
    for component, workload in workloads.items():
        assert selects(monitor["spec"]["selector"], workload["spec"]["template"]["metadata"]["labels"]), component
        ports = {p["name"] for c in workload["spec"]["template"]["spec"]["containers"] for p in c.get("ports", [])}
        assert endpoint["port"] in ports and endpoint["path"] == "/metrics", component


def test_scaled_object_scales_the_sim_statefulset_between_the_job_and_its_spares() -> None:
    objects = monitored_objects()
    (scaled,) = of_kind(objects, "ScaledObject")
    (sts,) = of_kind(objects, "StatefulSet")
    ref = scaled["spec"]["scaleTargetRef"]
    assert (ref["kind"], ref["name"]) == ("StatefulSet", sts["metadata"]["name"])
    assert scaled["spec"]["minReplicaCount"] <= sts["spec"]["replicas"] <= scaled["spec"]["maxReplicaCount"]
    config = load_job_config(ROOT / "configs" / "libero_10.yaml").job
    assert scaled["spec"]["minReplicaCount"] == config.num_stages * config.pods_per_stage
    (trigger,) = scaled["spec"]["triggers"]
    assert f'namespace="{sts["metadata"]["namespace"]}"' in trigger["metadata"]["query"]


def test_monitoring_and_autoscaling_are_opt_in() -> None:
    # Without the Prometheus Operator's or KEDA's CRDs installed, every overlay still applies.
    for target in TARGETS:
        assert not [o for o in build(target) if (o["apiVersion"], o["kind"]) in PUBLISHED_TYPES], target
    assert [o["kind"] for o in jobset_objects() if (o["apiVersion"], o["kind"]) in PUBLISHED_TYPES] == ["JobSet"]
