"""Mode use per episode (eval.mode_repeats, experiments.mode_repeats): whether a variant samples both modes of
one episode or picks one per episode. Pooled mode shares cannot tell the two apart; per episode, over its R
rollouts, the mode entropy (bits) and whether both modes occurred can.

    {{ mode_use_table(study="NAME") }}   per task: variant x seed rows (success, mean per-episode entropy, share
                                         of episodes with both modes), a seed-level row per variant (mean over
                                         seeds with the t-interval over the seeds' values), and the paired
                                         comparisons of an MDN variant with its deterministic twin
    {{ figure("mode_entropy", study="NAME") }}  per task, the distribution of per-episode entropy per variant

Everything comes from the runs' `<task>/modes_*` metrics and the `rollouts/modes/<task>.json` artifacts."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pandas as pd

from experiments.stats import SEED_COLUMN, interval, p_value, paired_comparison, pct, points, seed_interval
from reports.data.store import Study
from reports.plotting import FigureResult, gap, mark_gap, panel_grid, save, variant_color

REPEATS_METRIC = re.compile(r"^metrics\.(?P<task>[^/]+)/modes_repeats$")
# the mixture head against the deterministic head, each training alike (A, B): A - B per seed
PAIRS = (("ac-lstm-mdn", "ac-lstm"), ("lstm-mdn", "lstm"))
MEASURES = (("entropy", "entropy_bits_mean", "mean per-episode entropy (bits)"),
            ("both", "both_share", "episodes with both modes"))
NOTE = ("R rollouts per episode with distinct sampling seeds (repeat 0: the ordinary evaluation's rollout). "
        "entropy: per episode, the entropy in bits of the modes its R rollouts took (rollouts that took no mode "
        "left out; 0 = always one mode, 1 = an even split), averaged over the seed's episodes; both: share of "
        "the seed's episodes in which both modes occurred; success: the ordinary evaluation's. A variant row: "
        f"mean over seeds, with the {SEED_COLUMN} t-interval over the seeds' values (t with seeds - 1 degrees of "
        "freedom). A deterministic head (and an MDN that feeds back a mean) repeats one path: rolled once and "
        "counted R times, its entropy is 0 by construction. A − B: mean of the per-seed differences (same "
        "episodes per seed), t-interval over them, exact sign-flip p (with 3 seeds never below 0.25).")


def mode_use_tasks(study: Study) -> list[str]:
    """Evaluated tasks whose runs logged mode use per episode."""
    return sorted({m.group("task") for c in study.children.columns if (m := REPEATS_METRIC.match(c))
                   and study.children[c].notna().any()})


def mode_use_rows(study: Study) -> pd.DataFrame:
    """One row per (task, variant, seed) of the finished runs: repeats, success, entropy, both, between."""
    rows = []
    for task in mode_use_tasks(study):
        runs = study.ok[study.ok[f"metrics.{task}/modes_repeats"].notna()]
        for r in runs.to_dict("records"):
            rows.append({"eval_task": task, "variant": r["variant"], "seed": int(r["seed"]), "run_id": r["run_id"],
                         "repeats": int(r[f"metrics.{task}/modes_repeats"]),
                         "success": r.get(f"metrics.{task}/success_rate", math.nan),
                         "entropy": r.get(f"metrics.{task}/modes_entropy_bits_mean", math.nan),
                         "both": r.get(f"metrics.{task}/modes_both_share", math.nan),
                         "between": r.get(f"metrics.{task}/modes_between_share", math.nan)})
    cols = ["eval_task", "variant", "seed", "run_id", "repeats", "success", "entropy", "both", "between"]
    out = pd.DataFrame(rows, columns=cols)
    order = {v: i for i, v in enumerate(study.variants)}
    out["_v"] = out["variant"].map(order)
    return out.sort_values(["eval_task", "_v", "seed"], kind="stable").drop(columns="_v").reset_index(drop=True)


def variant_summary(rows: pd.DataFrame) -> pd.DataFrame:
    """Per (task, variant): each measure's mean over seeds and its seed-level t-interval (`<m>_low`, `<m>_high`;
    entropy bounded by 1 bit for two modes)."""
    out = []
    for (task, variant), part in rows.groupby(["eval_task", "variant"], sort=False):
        row = {"eval_task": task, "variant": variant, "seeds": len(part)}
        for m in ("success", "entropy", "both", "between"):
            values = part[m].to_numpy(dtype=float)
            row[m] = float(values.mean())
            row[f"{m}_low"], row[f"{m}_high"] = seed_interval(values)
        out.append(row)
    return pd.DataFrame(out)


def comparisons(rows: pd.DataFrame) -> pd.DataFrame:
    """Per task, PAIRS x MEASURES: the paired A − B comparison over the seeds both variants have."""
    out = []
    for task, part in rows.groupby("eval_task", sort=False):
        for a, b in PAIRS:
            pa, pb = part[part["variant"] == a], part[part["variant"] == b]
            if pa.empty or pb.empty:
                continue
            for key, _, label in MEASURES:
                c = paired_comparison(dict(zip(pa["seed"], pa[key], strict=True)),
                                      dict(zip(pb["seed"], pb[key], strict=True)))
                out.append({"eval_task": task, "A": a, "B": b, "measure": label, **c})
    return pd.DataFrame(out)


def even_coin_bits(repeats: int) -> float:
    """The mean per-episode entropy (bits) of a sampler that takes each of two modes with probability 1/2 in
    every one of `repeats` rollouts: below 1 bit, since R draws rarely split evenly (0.92 bits for R = 10)."""
    from math import comb

    def h(p: float) -> float:
        return 0.0 if p in (0.0, 1.0) else -(p * math.log2(p) + (1 - p) * math.log2(1 - p))

    return sum(comb(repeats, k) * h(k / repeats) for k in range(repeats + 1)) / 2 ** repeats


def _bits(x: float) -> str:
    return "–" if math.isnan(x) else f"{x:.2f}"


def _bits_interval(low: float, high: float) -> str:
    return "–" if math.isnan(low) else f"{low:.2f}–{high:.2f}"


def mode_use_markdown(study: Study, variant_label=str) -> str:
    """The {{ mode_use_table }} placeholder: per task a table of seeds and variants, then the comparisons."""
    rows = mode_use_rows(study)
    if rows.empty:
        return f"*Study `{study.name}` logged no mode use per episode (eval.mode_repeats).*\n"
    summary = variant_summary(rows)
    comp = comparisons(rows)
    out = []
    head = ["variant", "seed", "R", "success", "entropy (bits)", "both modes", "no mode (rollouts)"]
    for task, part in rows.groupby("eval_task", sort=False):
        lines = [f"**{task}**", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for variant, vpart in part.groupby("variant", sort=False):
            for r in vpart.to_dict("records"):
                lines.append(f"| {variant_label(variant)} | {r['seed']} | {r['repeats']} | {pct(r['success'])} | "
                             f"{_bits(r['entropy'])} | {pct(r['both'])} | {pct(r['between'])} |")
            s = summary[(summary["eval_task"] == task) & (summary["variant"] == variant)].iloc[0]
            lines.append(f"| **{variant_label(variant)}** | mean ({SEED_COLUMN}) | | "
                         f"**{pct(s['success'])}** ({interval(s['success_low'], s['success_high'])}) | "
                         f"**{_bits(s['entropy'])}** ({_bits_interval(s['entropy_low'], s['entropy_high'])}) | "
                         f"**{pct(s['both'])}** ({interval(s['both_low'], s['both_high'])}) | "
                         f"{pct(s['between'])} |")
        out.append("\n".join(lines))
        cpart = comp[comp["eval_task"] == task] if not comp.empty else comp
        if not cpart.empty:
            chead = ["A", "B", "measure", "A − B", "95% interval", "p", "seeds"]
            clines = ["| " + " | ".join(chead) + " |", "|" + "---|" * len(chead)]
            for c in cpart.to_dict("records"):
                bits = c["measure"].startswith("mean per-episode entropy")
                diff = f"{c['difference']:+.2f}" if bits else f"{points(c['difference'])} points"
                span = ("–" if math.isnan(c["low"]) else f"{c['low']:+.2f} to {c['high']:+.2f}" if bits
                        else f"{points(c['low'])} to {points(c['high'])}")
                clines.append(f"| {variant_label(c['A'])} | {variant_label(c['B'])} | {c['measure']} | {diff} | "
                              f"{span} | {p_value(c['p'])} | {c['n']} |")
            out.append("\n".join(clines))
    coin = "; ".join(f"R = {r}: {even_coin_bits(r):.2f} bits" for r in sorted(set(rows["repeats"])))
    return ("\n\n".join(out) + "\n\n" + NOTE + " A sampler that takes each mode with probability 1/2 in every "
            f"rollout averages less than 1 bit, as R draws rarely split evenly ({coin}).\n")


# ------------------------------------------------------------------------------------------------- figure
def mode_table(study: Study, run_id: str, task: str) -> dict | None:
    """The run's rollouts/modes/<task>.json, None when absent or unreadable (a gap)."""
    local = study._download(run_id, f"rollouts/modes/{task}.json")
    if local is None:
        return None
    try:
        return json.loads(Path(local).read_text())
    except (OSError, ValueError):
        return None


def mode_entropy(study: Study, folder: Path) -> FigureResult:
    """mode_entropy.png/.pdf: per task, the share of episodes (all seeds pooled) at each per-episode entropy
    (binned), one bar group per variant."""
    name, title = "mode_entropy", "Per-episode mode entropy over R sampled rollouts"
    rows = mode_use_rows(study)
    if rows.empty:
        return gap(name, title, "no run logged mode use per episode")
    tasks = list(dict.fromkeys(rows["eval_task"]))
    variants = list(dict.fromkeys(rows["variant"]))
    fig, axes = panel_grid(len(tasks), 5.0, 3.2, max_cols=2)
    edges = np.linspace(0.0, 1.0, 6)
    edges[-1] += 1e-9  # 1 bit in the last bin
    partial = []
    for ax, task in zip(axes.flat, tasks, strict=False):
        width = 0.8 / max(len(variants), 1)
        drawn = False
        for k, variant in enumerate(variants):
            values = []
            for run_id in rows[(rows["eval_task"] == task) & (rows["variant"] == variant)]["run_id"]:
                t = mode_table(study, run_id, task)
                if t is not None:
                    values.extend(t["entropy_bits"])
            if not values:
                partial.append(f"{task}: {variant}")
                continue
            share = np.histogram(np.clip(values, 0, 1), bins=edges)[0] / len(values)
            ax.bar(np.arange(len(share)) + (k - (len(variants) - 1) / 2) * width, share, width,
                   color=variant_color(variant, variants), label=f"{variant} ({len(values)} episodes)")
            drawn = True
        if not drawn:
            mark_gap(ax, "no per-episode mode tables")
        ax.set_xticks(range(len(edges) - 1), [f"{a:.1f}–{b:.1f}" for a, b in zip(edges[:-1], edges[1:], strict=True)],
                      fontsize=7)
        ax.set_xlabel("per-episode mode entropy (bits)", fontsize=8)
        ax.set_ylabel("share of episodes", fontsize=8)
        ax.set_title(task, fontsize=9)
        ax.legend(fontsize=7)
    fig.suptitle(title)
    return save(fig, folder, name, title, partial)
