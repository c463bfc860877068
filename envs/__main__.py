"""Command line of the envs package.

    python -m envs list
    python -m envs describe TASK [--json] [--seed N] [--cache-dir DIR]
    python -m envs render TASK --out FILE.png [--seed N] [--cache-dir DIR]   (also writes FILE.pdf)

An unknown task prints one line listing the known ones and exits with status 2.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Any

from envs.datasets import entry_paths, load_demos
from envs.tasks import Task, UnknownTaskError, get_task, task_class, task_names


def _describe(task: Task, seed: int, cache_dir: Path | None) -> dict[str, Any]:
    demos = load_demos(task, seed=seed, cache_dir=cache_dir)
    meta, L = demos.meta, task.layout
    episode = task.episodes(1, seed=0)[0]
    return {
        "task": task.name,
        "model_task": task.model_task,
        "seed": seed,
        "demonstrations": len(demos),
        "lengths": {"min": int(demos.lengths.min()), "max": int(demos.lengths.max()),
                    "mean": round(float(demos.lengths.mean()), 2)},
        "step_seconds": task.step_seconds,
        "state": {"dim": L.dim, "dq": L.n_joints, "grip": int(L.gripper), "phi": L.phi_dim, "psi": L.psi_dim,
                  "names": L.names},
        "expert_success": meta.get("expert_success"),
        "rejections": meta.get("rejections"),
        "generation_seconds": meta.get("generation_seconds"),
        "episode_horizon": episode.horizon,
        "episode_info_keys": sorted(episode.info),
        "cache": str(entry_paths(task, seed, cache_dir)[0]),
        "config_hash": meta.get("config_hash"),
    }


def _print_description(d: dict[str, Any]) -> None:
    s, lens = d["state"], d["lengths"]
    shared = "" if d["model_task"] == d["task"] else f" (trained on the {d['model_task']!r} demonstrations)"
    print(f"task: {d['task']}{shared}")
    print(f"demonstrations: {d['demonstrations']} (seed {d['seed']}), {lens['min']}-{lens['max']} steps "
          f"(mean {lens['mean']}) of {d['step_seconds']} s")
    print(f"state: {s['dim']} dims = dq {s['dq']} + grip {s['grip']} + phi {s['phi']} + psi {s['psi']}")
    print(f"  names: {', '.join(s['names'])}")
    print(f"expert success in physics: {100 * d['expert_success']:.0f}% of the kept demonstrations; "
          f"rejected and resampled: {d['rejections']}")
    print(f"generation time: {d['generation_seconds']:.1f} s")
    print(f"evaluation episodes: horizon {d['episode_horizon']} steps; info: {', '.join(d['episode_info_keys'])}")
    print(f"cache: {d['cache']}")


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m envs", description="Sawyer tasks and their demonstrations.")
    sub = ap.add_subparsers(dest="command", required=True)
    sub.add_parser("list", help="the registered tasks")
    for name, helptext in [("describe", "dataset counts, lengths, state layout, expert success, timing"),
                           ("render", "3D figure of the demonstrations' tip paths (PNG + PDF)")]:
        p = sub.add_parser(name, help=helptext)
        p.add_argument("task")
        p.add_argument("--seed", type=int, default=0)
        p.add_argument("--cache-dir", type=Path, default=None, help="default: $ACRMDN_CACHE or ~/.cache/acrmdn")
        if name == "describe":
            p.add_argument("--json", action="store_true", help="machine-readable output")
        else:
            p.add_argument("--out", type=Path, required=True, help="PNG path; the PDF goes beside it")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    if args.command == "list":
        for name in sorted(task_names()):
            cls = task_class(name)
            note = "" if cls.model_task in ("", name) else f"  (evaluation; model trained on {cls.model_task})"
            doc = (cls.__dict__.get("__doc__") or "").strip().splitlines()
            print(f"{name}{note}" + (f"  - {doc[0]}" if doc else ""))
        return 0
    try:
        task = get_task(args.task)
    except UnknownTaskError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.command == "describe":
        d = _describe(task, args.seed, args.cache_dir)
        if args.json:
            print(json.dumps(d, indent=1))
        else:
            _print_description(d)
        return 0
    from envs.render import render_task

    own_data = task.model_task in ("", task.name)  # else: the expert on a few of its evaluation episodes
    demos = load_demos(task, seed=args.seed, cache_dir=args.cache_dir) if own_data else None
    for path in render_task(task, demos, args.out):
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
