"""The Kubernetes API contract of the overlays: ``kubectl apply -k``, a second apply and
``kubectl delete -k`` run for real against kmock's emulated API server on loopback, and the
requests kubectl makes are the contract: each object of ``kubectl kustomize`` is created at its
API path (group, version, namespace, plural) with the body kustomize rendered, applying again
changes nothing, and delete removes every object.

kmock 0.8 needs two fixes to serve kubectl, both made here and nowhere else:

- its core-group discovery (``GET /api/v1``) says ``groupVersion: "/v1"``, which kubectl cannot
  map to kinds, so the test serves that document itself through kmock's own reactions, built
  from kmock's bundled discovery data (a real cluster's, see ``ResourcesArray.load_bundled``);
- its path parser reads ``/api/v1/namespaces[/<name>]`` as the namespace prefix of some other
  resource (``POST /api/v1/namespaces`` even fails to parse), so Namespace objects cannot be
  created, read or deleted; the test wraps the parser so that those paths address the
  Namespace objects themselves, as the real API server does.

What kmock does not emulate, and so these tests do not cover: OpenAPI documents (kubectl runs
with ``--validate=false``; test_k8s.py validates every object against the API schemas
instead), server-set fields (uid, resourceVersion, defaults), strategic merge patches (kmock
merges patches as plain JSON merge patches) and server-side apply of an object that does not
exist yet (kmock answers a PATCH to a missing object with 404, so server-side apply is tested as
the second apply only).
"""

from __future__ import annotations

import asyncio
import json
import os
import warnings
from pathlib import Path
from typing import Any

import pytest
from kmock import KubernetesEmulator, Request, ResourcesArray, resource
from kmock._internal import parsing

from support.k8s_manifests import TARGETS, build, kubectl_path

OVERLAYS = ("dev-cpu", "gpu-cluster")
LAST_APPLIED = "kubectl.kubernetes.io/last-applied-configuration"
KUBECTL_TIMEOUT_S = 30
# What kubectl sends a create, an update or a server-side apply as.
JSON = "application/json"
STRATEGIC_MERGE_PATCH = "application/strategic-merge-patch+json"
APPLY_PATCH = "application/apply-patch+yaml"

pytestmark = [pytest.mark.asyncio, pytest.mark.timeout(120)]


# --- the emulated API server -------------------------------------------------------------------


def _discovery() -> ResourcesArray:
    resources = ResourcesArray()
    with warnings.catch_warnings():
        # kmock 0.8 reads its bundled data with a deprecated importlib.resources call.
        warnings.simplefilter("ignore", DeprecationWarning)
        resources.load_bundled()
    return resources


# A real cluster's discovery, as kmock bundles it: the kinds, plurals and scopes kubectl maps.
DISCOVERY = _discovery()


def core_discovery(resources: ResourcesArray) -> dict[str, Any]:
    """The ``GET /api/v1`` document (APIResourceList) of the core group's ``resources``."""
    listed = []
    for res in sorted(resources, key=lambda r: r.plural or ""):
        if res.group != "" or res.version != "v1":
            continue
        info = resources[res]
        listed.append(
            {
                "name": res.plural,
                "singularName": info.singular or "",
                "namespaced": bool(info.namespaced),
                "kind": info.kind,
                "verbs": sorted(info.verbs),
                "shortNames": sorted(info.shortnames),
            }
        )
    return {"kind": "APIResourceList", "apiVersion": "v1", "groupVersion": "v1", "resources": listed}


_kmock_parse_path = parsing.parse_path


def parse_path_with_namespace_objects(path: str) -> parsing.ParsedPath:
    """kmock's parse of an API path, except that ``/api/v1/namespaces`` and
    ``/api/v1/namespaces/<name>[/status|/finalize]`` address Namespace objects, not a namespace."""
    parts = path.strip("/").split("/")
    if parts[:3] == ["api", "v1", "namespaces"] and (
        len(parts) <= 4 or (len(parts) == 5 and parts[4] in ("status", "finalize"))
    ):
        return parsing.ParsedPath(
            group="",
            version="v1",
            plural="namespaces",
            name=parts[3] if len(parts) > 3 else None,
            subresource=parts[4] if len(parts) > 4 else None,
        )
    return _kmock_parse_path(path)


@pytest.fixture
def api_server(kmock: KubernetesEmulator, monkeypatch: pytest.MonkeyPatch) -> KubernetesEmulator:
    """kmock's Kubernetes emulator (from its pytest plugin, on a free loopback port) serving a
    real cluster's discovery, core group and Namespace objects included."""
    monkeypatch.setattr(parsing, "parse_path", parse_path_with_namespace_objects)
    for res, info in DISCOVERY.items():
        kmock.resources[res] = info
    kmock["get /api/v1"] << (lambda: core_discovery(kmock.resources))
    return kmock


# --- kubectl -----------------------------------------------------------------------------------


class Kubectl:
    """``kubectl`` pointed at one API server with an empty kubeconfig and its own cache."""

    def __init__(self, server: str, home: Path) -> None:
        kubeconfig = home / "kubeconfig"
        kubeconfig.write_text("")
        self.server = server
        self.cache = home / "cache"
        # The server is on loopback: no proxy may stand between kubectl and it.
        self.env = {k: v for k, v in os.environ.items() if k.lower() not in ("http_proxy", "https_proxy", "all_proxy")}
        self.env |= {"KUBECONFIG": str(kubeconfig), "NO_PROXY": "127.0.0.1", "HOME": str(home)}

    async def __call__(self, *args: str, stdin: str | None = None) -> str:
        """kubectl's stdout; fails the test if it exits non-zero or runs past its time limit."""
        argv = [kubectl_path(), *args, "--server", self.server, "--cache-dir", str(self.cache)]
        proc = await asyncio.create_subprocess_exec(
            *argv,
            env=self.env,
            stdin=asyncio.subprocess.PIPE,
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.PIPE,
        )
        try:
            out, err = await asyncio.wait_for(
                proc.communicate(stdin.encode() if stdin is not None else None), KUBECTL_TIMEOUT_S
            )
        finally:
            if proc.returncode is None:
                proc.kill()
                await proc.wait()
        assert proc.returncode == 0, f"kubectl {' '.join(args)} exited {proc.returncode}:\n{err.decode()}"
        return out.decode()


@pytest.fixture
def kubectl(api_server: KubernetesEmulator, tmp_path: Path) -> Kubectl:
    return Kubectl(str(api_server.url).rstrip("/"), tmp_path)


async def apply(kubectl: Kubectl, overlay: str, *flags: str) -> str:
    # No OpenAPI documents on the emulator: schemas are test_k8s.py's job.
    return await kubectl("apply", "-k", str(TARGETS[overlay]), "--validate=false", *flags)


# --- the contract ------------------------------------------------------------------------------


def resource_of(obj: dict[str, Any]) -> resource:
    """The API resource (group, version, plural) that serves ``obj``'s kind, from discovery."""
    group, _, version = obj["apiVersion"].rpartition("/")
    (found,) = [r for r in DISCOVERY if (r.group, r.version) == (group, version) and DISCOVERY[r].kind == obj["kind"]]
    return found


def namespace_of(obj: dict[str, Any]) -> str | None:
    """The namespace ``obj`` lives in, None for a cluster-scoped kind."""
    return obj["metadata"]["namespace"] if DISCOVERY[resource_of(obj)].namespaced else None


def collection_path(obj: dict[str, Any]) -> str:
    """The path kubectl creates ``obj`` at: its kind's collection, in its namespace if it has one."""
    res = resource_of(obj)
    prefix = f"/api/{res.version}" if res.group == "" else f"/apis/{res.group}/{res.version}"
    namespace = namespace_of(obj)
    scope = f"/namespaces/{namespace}" if namespace is not None else ""
    return f"{prefix}{scope}/{res.plural}"


def object_path(obj: dict[str, Any]) -> str:
    return f"{collection_path(obj)}/{obj['metadata']['name']}"


def key_of(obj: dict[str, Any]) -> tuple[resource, str | None, str]:
    """Where kmock keeps ``obj``: ``api_server.objects[key_of(obj)]``."""
    return resource_of(obj), namespace_of(obj), obj["metadata"]["name"]


def without_last_applied(body: dict[str, Any]) -> dict[str, Any]:
    """``body`` less the annotation kubectl's client-side apply adds (and the then empty map)."""
    stripped = json.loads(json.dumps(body))
    annotations = stripped["metadata"].get("annotations", {})
    annotations.pop(LAST_APPLIED, None)
    if not annotations:
        stripped["metadata"].pop("annotations", None)
    return stripped


def requests(api_server: KubernetesEmulator, method: str, since: int = 0) -> list[Request]:
    """The requests with HTTP ``method`` the server got, from the ``since``-th request on."""
    return [r for r in list(api_server)[since:] if r.method.value == method]


def snapshot(api_server: KubernetesEmulator, objects: tuple[dict[str, Any], ...]) -> list[dict[str, Any]]:
    """The stored state of each of ``objects``, as plain JSON."""
    return [json.loads(json.dumps(api_server.objects[key_of(o)].raw)) for o in objects]


def is_stored(api_server: KubernetesEmulator, obj: dict[str, Any]) -> bool:
    key = key_of(obj)
    return key in api_server.objects and not api_server.objects[key].deleted


@pytest.mark.parametrize("overlay", OVERLAYS)
async def test_apply_creates_every_object_at_its_api_path(
    overlay: str, api_server: KubernetesEmulator, kubectl: Kubectl
) -> None:
    objects = build(overlay)
    await apply(kubectl, overlay)
    created = [(r.url.path, r.params.get("fieldManager")) for r in requests(api_server, "POST")]
    assert created == [(collection_path(o), "kubectl-client-side-apply") for o in objects]
    assert all(is_stored(api_server, o) for o in objects)


@pytest.mark.parametrize("overlay", OVERLAYS)
async def test_apply_sends_each_object_as_kustomize_renders_it(
    overlay: str, api_server: KubernetesEmulator, kubectl: Kubectl
) -> None:
    objects = build(overlay)
    await apply(kubectl, overlay)
    posts = requests(api_server, "POST")
    assert [r.headers["Content-Type"] for r in posts] == [JSON] * len(objects)
    for request, obj in zip(posts, objects, strict=True):
        where = f"{obj['kind']}/{obj['metadata']['name']}"
        assert without_last_applied(request.data) == obj, where
        # The annotation is what the next apply diffs against: the object as rendered.
        last_applied = json.loads(request.data["metadata"]["annotations"][LAST_APPLIED])
        assert without_last_applied(last_applied) == obj, where


@pytest.mark.parametrize("overlay", OVERLAYS)
async def test_apply_creates_the_namespace_before_anything_in_it(
    overlay: str, api_server: KubernetesEmulator, kubectl: Kubectl
) -> None:
    objects = build(overlay)
    await apply(kubectl, overlay)
    created = [r.url.path for r in requests(api_server, "POST")]
    (namespace,) = [o["metadata"]["name"] for o in objects if o["kind"] == "Namespace"]
    assert created[0] == "/api/v1/namespaces"
    assert all(f"/namespaces/{namespace}/" in path for path in created[1:])


@pytest.mark.parametrize("overlay", OVERLAYS)
async def test_second_apply_creates_nothing_and_changes_nothing(
    overlay: str, api_server: KubernetesEmulator, kubectl: Kubectl
) -> None:
    objects = build(overlay)
    await apply(kubectl, overlay)
    before, since = snapshot(api_server, objects), len(api_server)
    await apply(kubectl, overlay)
    assert not requests(api_server, "POST", since) and not requests(api_server, "DELETE", since)
    # kubectl may still send strategic merge patches (here it re-sends the PodDisruptionBudget's
    # selector, whose patch strategy is "replace"); any it sends must leave the object as it is.
    patches = requests(api_server, "PATCH", since)
    assert {r.headers["Content-Type"] for r in patches} <= {STRATEGIC_MERGE_PATCH}
    assert {r.url.path for r in patches} <= {object_path(o) for o in objects}
    assert snapshot(api_server, objects) == before


@pytest.mark.parametrize("overlay", OVERLAYS)
async def test_server_side_apply_patches_every_object_in_place(
    overlay: str, api_server: KubernetesEmulator, kubectl: Kubectl
) -> None:
    objects = build(overlay)
    await apply(kubectl, overlay)
    before, since = snapshot(api_server, objects), len(api_server)
    await apply(kubectl, overlay, "--server-side")
    applied = [r for r in requests(api_server, "PATCH", since) if r.params.get("fieldManager") == "kubectl"]
    assert [r.url.path for r in applied] == [object_path(o) for o in objects]
    assert {r.headers["Content-Type"] for r in applied} == {APPLY_PATCH}
    for request, obj in zip(applied, objects, strict=True):
        assert request.data == obj, f"{obj['kind']}/{obj['metadata']['name']}"
    assert not requests(api_server, "POST", since)
    assert snapshot(api_server, objects) == before


@pytest.mark.parametrize("overlay", OVERLAYS)
async def test_apply_after_an_edit_patches_only_the_edited_field(
    overlay: str, api_server: KubernetesEmulator, kubectl: Kubectl
) -> None:
    objects = build(overlay)
    await apply(kubectl, overlay)
    sts = next(o for o in objects if o["kind"] == "StatefulSet")
    edited = json.loads(json.dumps(sts))
    edited["spec"]["replicas"] = sts["spec"]["replicas"] + 1
    since = len(api_server)
    await kubectl("apply", "-f", "-", "--validate=false", stdin=json.dumps(edited))
    (patch,) = requests(api_server, "PATCH", since)
    assert patch.url.path == object_path(sts)
    assert patch.headers["Content-Type"] == STRATEGIC_MERGE_PATCH
    assert without_last_applied(patch.data) == {"metadata": {}, "spec": {"replicas": edited["spec"]["replicas"]}}
    assert api_server.objects[key_of(sts)]["spec"]["replicas"] == edited["spec"]["replicas"]


@pytest.mark.parametrize("overlay", OVERLAYS)
async def test_delete_removes_every_object(overlay: str, api_server: KubernetesEmulator, kubectl: Kubectl) -> None:
    objects = build(overlay)
    await apply(kubectl, overlay)
    since = len(api_server)
    await kubectl("delete", "-k", str(TARGETS[overlay]))
    deleted = [r.url.path for r in requests(api_server, "DELETE", since)]
    assert deleted == [object_path(o) for o in objects]
    assert not any(is_stored(api_server, o) for o in objects)
