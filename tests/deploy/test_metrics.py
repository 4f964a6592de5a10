"""The metrics docs/kubernetes.md lists are the ones a real pod and controller export, and the alert
rules (k8s/components/monitoring/rules.yaml) name only those: one small job (a controller and
two gym pods, real processes on loopback) is driven through a reset, steps and refused
requests, then scraped."""

from __future__ import annotations

import asyncio
import re
import threading
from collections.abc import Iterator

import httpx
import numpy as np
import promql_parser
import pytest
import yaml
from prometheus_client.parser import text_string_to_metric_families
from support.service_procs import job_config, local_job, post_wire, reset_body, step_body

from service.pod.metrics import PodMetrics
from service.pod.settings import PodSettings
from service.pod.state import PodState
from service.runner import LocalJob
from support import ROOT

DOCS = ROOT / "docs" / "kubernetes.md"
RULES = ROOT / "k8s" / "components" / "monitoring" / "rules.yaml"


def documented(server: str) -> set[str]:
    """The metric names of ``server`` (``pod``, ``controller``) in the docs' Monitoring section."""
    text = DOCS.read_text()
    section = text[text.index("## Monitoring") :]
    section = section[: section.index("\n## ", 1)]
    return set(re.findall(rf"^\| `(vecsim_{server}_\w+)` \|", section, re.MULTILINE))


def documented_alerts() -> set[str]:
    text = DOCS.read_text()
    return set(re.findall(r"^\| `(Vecsim\w+)` \|", text, re.MULTILINE))


def scrape(url: str) -> dict[str, set[str]]:
    """``{exported name: sample names}``: counters as ``<name>_total``, others by family name.
    The ``<name>_created`` series prometheus_client adds beside each counter and histogram (its
    creation time, read back as families of their own) go with their metric."""
    families = list(text_string_to_metric_families(httpx.get(f"{url}/metrics", timeout=5).text))
    exported = {f"{f.name}_total" if f.type == "counter" else f.name: {s.name for s in f.samples} for f in families}
    created = {f"{f.name}_created" for f in families if f.type in ("counter", "histogram")}
    return {name: samples for name, samples in exported.items() if name not in created}


def selector_names(expr: str) -> set[str]:
    """The metric names an expression reads (every vector selector, range selectors' included)."""
    names: set[str] = set()

    def visit(node: object) -> None:
        if isinstance(node, promql_parser.VectorSelector) and node.name:
            names.add(node.name)

    promql_parser.walk(promql_parser.parse(expr), visit)
    return names


def alert_rules() -> list[dict[str, str]]:
    rules = yaml.safe_load(RULES.read_text())
    return [rule for group in rules["spec"]["groups"] for rule in group["rules"]]


@pytest.fixture(scope="module")
def driven_job() -> Iterator[tuple[LocalJob, dict[str, dict[str, set[str]]]]]:
    job = {
        "job_id": "metrics",
        "suite": None,
        "tasks": ["gym/Pendulum-v1"],
        "group_size": 2,
        "num_stages": 2,
        "pods_per_stage": 1,
        "camera": {"names": []},
        "max_episode_steps": 5,
    }
    with local_job(job_config(job, replicas=2, max_envs=4)) as running:
        routing = running.wait_ready(timeout=120)
        pod = routing.stages[0].pods[0]
        generation = routing.generation
        # A reset, a step, a refused call on a pod; a refused call on the controller.
        assert post_wire(pod.url, "reset", reset_body(generation, [0], [0]), running.token).status_code == 200
        actions = np.zeros((1, 1), np.float32)
        assert post_wire(pod.url, "step", step_body(generation, [0], actions), running.token).status_code == 200
        assert post_wire(pod.url, "step", step_body(generation, [0], actions), None).status_code == 401
        assert httpx.post(f"{running.controller_url}/v1/pods", json={}, timeout=5).status_code == 401
        scraped = {"pod": scrape(pod.url), "controller": scrape(running.controller_url)}
        yield running, scraped


@pytest.mark.slow
@pytest.mark.parametrize("server", ["pod", "controller"])
def test_every_documented_metric_is_exported_and_every_exported_one_documented(driven_job, server: str) -> None:
    _, scraped = driven_job
    assert documented(server) == set(scraped[server])


@pytest.mark.slow
@pytest.mark.parametrize("server", ["pod", "controller"])
def test_every_metric_has_samples_once_the_job_ran(driven_job, server: str) -> None:
    _, scraped = driven_job
    assert [name for name, samples in scraped[server].items() if not samples] == []


@pytest.mark.slow
def test_alert_rules_read_only_exported_metrics(driven_job) -> None:
    _, scraped = driven_job
    samples = set().union(*(names for server in scraped.values() for names in server.values()))
    for rule in alert_rules():
        unknown = selector_names(rule["expr"]) - samples
        assert unknown == set(), f"{rule['alert']} reads {sorted(unknown)}, which no server exports"


def test_every_alert_is_documented() -> None:
    assert {rule["alert"] for rule in alert_rules()} == documented_alerts()


def test_the_parser_finds_names_inside_functions_aggregations_and_ranges() -> None:
    expr = "histogram_quantile(0.9, sum by (le) (rate(a_bucket[5m]))) > on() group_left b or c offset 1m"
    assert selector_names(expr) == {"a_bucket", "b", "c"}


@pytest.mark.slow
def test_idle_envs_count_envs_without_an_episode(driven_job) -> None:
    running, _ = driven_job
    routing = running.wait_ready(timeout=60)
    pod = routing.stages[1].pods[0]

    def idle() -> float:
        (family,) = [
            f
            for f in text_string_to_metric_families(httpx.get(f"{pod.url}/metrics", timeout=5).text)
            if f.name == "vecsim_pod_idle_envs"
        ]
        return family.samples[0].value

    envs = httpx.get(f"{pod.url}/v1/info", headers={"Accept": "application/json"}, timeout=5).json()["num_envs"]
    assert idle() == envs
    body = reset_body(routing.generation, [0, 1], [0, 1])
    assert post_wire(pod.url, "reset", body, running.token).status_code == 200
    assert idle() == envs - 2
    # Pendulum truncates at max_episode_steps (5): the env is idle again after its fifth step.
    step = step_body(routing.generation, [0], np.zeros((1, 1), np.float32))
    for _ in range(5):
        assert post_wire(pod.url, "step", step, running.token).status_code == 200
    assert idle() == envs - 1


def test_queued_calls_count_calls_waiting_for_the_sim_thread() -> None:
    metrics = PodMetrics()
    state = PodState(PodSettings(), metrics)
    running, release = threading.Event(), threading.Event()

    def hold() -> None:
        running.set()
        release.wait(10)

    def queued() -> float | None:
        return metrics.registry.get_sample_value("vecsim_pod_queued_calls")

    async def scenario() -> list[float | None]:
        try:
            first = asyncio.ensure_future(state.run(hold))
            await asyncio.to_thread(running.wait, 10)
            second = asyncio.ensure_future(state.run(lambda: None))
            await asyncio.sleep(0)
            seen = [queued()]
            release.set()
            await asyncio.gather(first, second)
            return [*seen, queued()]
        finally:
            release.set()
            await state.close()

    # The first call holds the sim thread; the second waits for it, then both are done.
    assert asyncio.run(scenario()) == [1.0, 0.0]
