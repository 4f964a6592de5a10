"""The GPU benches' plots: scaling against linear, pipelining against one stage."""

from __future__ import annotations

import statistics
from pathlib import Path
from typing import Any

import numpy as np
from .records import img_dir

from .stats import PIPELINE_TARGET, waiting


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_scaling(summary: dict[str, Any], tag: str) -> list[Path]:
    """Env-steps/s against pods (service alone and the loop, each against its linear), and
    where a step's time goes; return the PNG paths."""
    plt = _pyplot()
    setup = summary["setup"]
    counts = list(setup["pod_counts"])
    fig, ax = plt.subplots(figsize=(6.0, 4.0))
    for kind, color, label in (
        ("service", "tab:blue", "service alone (scripted actions)"),
        ("loop", "tab:orange", "EnvLoop + ResNet-18 (graphed), 1 stage"),
        ("loop_per_pod", "tab:green", "EnvLoop + ResNet-18, a stage per pod"),
    ):
        if kind not in summary:
            continue
        rates = [summary[kind][f"pods={p}"]["env_steps_per_s"] for p in counts]
        med = [r["median"] for r in rates]
        ax.errorbar(
            counts,
            med,
            yerr=[[m - r["min"] for m, r in zip(med, rates)], [r["max"] - m for m, r in zip(med, rates)]],
            marker="o",
            capsize=3,
            color=color,
            label=label,
        )
        if counts[0] == 1 and kind != "loop_per_pod":  # its 1-pod figure is the loop's
            ax.plot(counts, [med[0] * p for p in counts], "--", color=color, alpha=0.5, label=f"linear ({kind})")
    physical = summary["topology"]["physical_cores"]
    if counts[-1] > physical:
        ax.axvline(physical + 0.5, color="grey", linestyle=":", label=f"{physical} physical cores")
    ax.set_xticks(counts)
    ax.set_xlabel("pods (one CPU each)")
    ax.set_ylabel("env-steps/s")
    ax.set_title(
        f"{setup['suite']}: {setup['envs_per_pod']} envs/pod ({len(setup['tasks'])} tasks), "
        f"{setup['size']}px x {len(camera_names(setup))} cameras",
        fontsize=9,
    )
    ax.legend(fontsize=7)
    fig.tight_layout()
    paths = [img_dir() / f"gpu_scale{tag}_pods.png"]
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    fig, (left, right) = plt.subplots(1, 2, figsize=(10.0, 4.0))
    x = np.arange(len(counts))
    split = [summary["loop"][f"pods={p}"]["time_split_ms"] for p in counts]
    bottom = np.zeros(len(counts))
    for label, values in (
        ("policy", [s["policy_ms"] for s in split]),
        ("physics", [s["physics_ms_per_pod"] for s in split]),
        ("render", [s["render_ms_per_pod"] for s in split]),
        (
            "pod: rest (IPC)",
            [max(s["pod_step_ms"] - s["physics_ms_per_pod"] - s["render_ms_per_pod"], 0) for s in split],
        ),
        ("serving (HTTP, codec, slowest pod)", [s["serving_ms"] for s in split]),
    ):
        left.bar(x, values, bottom=bottom, label=label)
        bottom += np.array(values)
    left.set_xticks(x, [str(p) for p in counts])
    left.set_xlabel("pods")
    left.set_ylabel("ms per loop step")
    left.set_title("EnvLoop: where a step goes (physics/render: worker s per pod)", fontsize=9)
    left.legend(fontsize=7)
    service = [summary["service"][f"pods={p}"] for p in counts]
    width = 0.27
    for offset, (label, values) in enumerate(
        (
            ("pod step (its /metrics)", [s["time_split_ms"]["pod_step_ms"] for s in service]),
            ("round trip, mean pod", [s["slowest_pod"]["pod_round_trip_mean_ms"] or 0 for s in service]),
            ("round trip, slowest pod", [s["slowest_pod"]["pod_round_trip_slowest_ms"] or 0 for s in service]),
        )
    ):
        right.bar(x + (offset - 1) * width, values, width, label=label)
    right.plot(x, [s["time_split_ms"]["stage_call_ms"] for s in service], "k_", markersize=18, label="stage call")
    right.set_xticks(x, [str(p) for p in counts])
    right.set_xlabel("pods")
    right.set_ylabel("ms per call")
    right.set_title("service alone: a call waits for its slowest pod", fontsize=9)
    right.legend(fontsize=7)
    fig.tight_layout()
    paths.append(img_dir() / f"gpu_scale{tag}_split.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)
    return paths


def plot_pipeline(summary: dict[str, Any], tag: str) -> list[Path]:
    """1 against 2 stages (env-steps/s) and the per-call times behind them; return the PNG path."""
    plt = _pyplot()
    loop, policy = summary["loop"], summary["policy"]
    fig, (left, right) = plt.subplots(1, 2, figsize=(10.0 + 1.5 * len(summary.get("batch_wait", [])), 4.0))
    layouts = list(summary["speedup_2_vs_1"])
    lockstep = ["stages=1/lockstep"] if "stages=1/lockstep" in loop else []
    waits = [entry["batch_wait_s"] for entry in summary.get("batch_wait", [])]  # --compare-batch-wait-s
    names = [*lockstep, "stages=1", *(f"{layout}/stages=2" for layout in layouts)]
    labels = [
        *(["1 stage\n(lockstep)"] if lockstep else []),
        "1 stage\n(all pods)",
        *(f"2 stages\n({layout})" for layout in layouts),
    ]
    for wait in waits:
        names += [waiting(layout, wait) for layout in layouts]
        labels += [f"2 stages\n({layout},\nwait {wait:g} s)" for layout in layouts]
    base = len(names) - len(waits) * len(layouts)
    more = summary["setup"].get("compare_stages", [])  # --compare-stages: slices in n stages
    for n in more:
        names += [f"slices/stages={n}", *(waiting("slices", wait, n) for wait in waits)]
        labels += [f"{n} stages\n(slices)", *(f"{n} stages\n(slices,\nwait {wait:g} s)" for wait in waits)]
    rates = [loop[name]["env_steps_per_s"]["median"] for name in names]
    extra = ["tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan"]
    colours = ["tab:gray", "tab:blue", "tab:orange", "tab:green"][-base:] + [
        extra[i % len(extra)] for i in range(len(names) - base)
    ]
    bars = left.bar(labels, rates, color=colours)
    left.bar_label(bars, fmt="%.1f", fontsize=8)
    left.tick_params(axis="x", labelsize=7 if len(names) > 4 else 10)
    left.set_ylabel("env-steps/s")
    ratios = ", ".join(f"{layout} {r['median']:.2f}x" for layout, r in summary["speedup_2_vs_1"].items())
    if lockstep:
        over = summary["speedup_2_vs_1_lockstep"]
        ratios += (
            "\n(over 1 stage in lockstep: "
            + ", ".join(f"{layout} {r['median']:.2f}x" for layout, r in over.items())
            + ")"
        )
    left.set_title(f"pipelining at K={policy.get('chunk', 1)}: {ratios} (target {PIPELINE_TARGET}x)", fontsize=9)
    x = np.arange(len(names))
    width = 0.27
    sizes = summary["setup"]["stage_envs_by_layout"]
    alone = [policy["forward_ms"].get(str(policy["target_batch"]), 0)] * (1 + len(lockstep)) + [
        statistics.mean(policy["forward_ms"].get(str(sum(stage)), 0) for stage in sizes[layout])
        for layout in [
            *layouts * (1 + len(waits)),
            *(f"slices/stages={n}" for n in more for _ in range(1 + len(waits))),
        ]
    ]
    for offset, (label, values) in enumerate(
        (
            ("stage call (loop)", [loop[name]["time_split_ms"]["stage_call_ms"] for name in names]),
            ("policy per call (loop)", [loop[name]["time_split_ms"]["policy_ms"] for name in names]),
            ("policy alone" + (" (CUDA graph)" if policy["cuda_graphs"] else " (eager)"), alone),
        )
    ):
        right.bar(x + (offset - 1) * width, values, width, label=label)
    right.set_xticks(x, labels if waits else [label.replace("\n", " ") for label in labels], fontsize=7)
    right.set_ylabel("ms")
    right.set_title(f"{policy['name'].split(' + ')[0]}", fontsize=8)
    right.legend(fontsize=7)
    fig.tight_layout()
    path = img_dir() / f"gpu_scale{tag}_stages.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return [path]


def camera_names(setup: dict[str, Any]) -> list[str]:
    """The cameras of a run's setup."""
    return list(setup["camera"]["names"])
