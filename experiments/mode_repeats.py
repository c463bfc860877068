"""Mode use per episode: each evaluation episode of a task with modes (a `modes` attribute naming them, and
`mode_<name>` one-hot labels in its evaluate) rolled out R times with distinct sampling seeds (`eval.mode_repeats`).

Pooled mode shares cannot tell a policy that samples both modes of an episode from a deterministic one that
splits the episodes between the modes by geometry; per-episode repeats can. Per episode, over its R rollouts:
the mode entropy in bits (over the rollouts that took a mode: 0 = always the same mode, 1 = an even split of
two modes) and whether both (every) mode occurred. A rollout that took no mode (`between`: averaged, collided,
or never crossed) is counted apart, so an episode whose rollouts all failed that way has entropy 0.

Repeat 0 is the ordinary evaluation's rollout (its sampling seed is the training seed), so the success of the
evaluation is unchanged; repeat r >= 1 samples with `repeat_seed(seed, r)`, reproducible from (seed, r). A
model whose rollouts do not sample (a deterministic head, or an MDN feeding back a mean) gives the same path
every time: it is rolled once and that rollout counted R times (`deterministic` in the table says so).

Logged per evaluated task E: `E/modes_repeats`, `E/modes_entropy_bits_mean`, `E/modes_both_share` (share of
episodes in which every mode occurred), `E/modes_share_<name>` and `E/modes_between_share` (shares of all
episode x repeat rollouts), and the artifact `rollouts/modes/E.json` (`mode_table`)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

SAMPLING_FEEDBACKS = ("sample", "sample_component", "segment_component", "segment_track")  # stm.rollout
MODES_DIR = "rollouts/modes"  # artifact folder of the per-episode tables (the study export keeps it)


def task_modes(task) -> tuple[str, ...]:
    """The mode names of a task (its `modes` attribute), () for a task without modes."""
    return tuple(getattr(task, "modes", ()) or ())


def repeat_seed(train_seed: int, repeat: int) -> int:
    """The sampling seed of repeat `repeat` of a model trained with `train_seed`: repeat 0 keeps the ordinary
    evaluation's seed (the training seed); later repeats get seeds derived from (train_seed, repeat), distinct
    from each other and from every training seed's evaluation seed."""
    if repeat < 0:
        raise ValueError(f"repeat must be >= 0, got {repeat}")
    if repeat == 0:
        return int(train_seed)
    return int(np.random.SeedSequence([int(train_seed) & 0xFFFFFFFF, repeat]).generate_state(1)[0]) + (1 << 32)


def rollout_modes(results: list[dict[str, Any]], names: tuple[str, ...]) -> np.ndarray:
    """(B,) int: the index of the mode each rollout took (its `mode_<name>` label is 1), -1 for none."""
    out = np.full(len(results), -1, dtype=int)
    for b, r in enumerate(results):
        for i, name in enumerate(names):
            if float(r.get(f"mode_{name}", 0.0)) >= 0.5:
                out[b] = i
                break
    return out


def entropy_bits(modes: np.ndarray, n_modes: int) -> np.ndarray:
    """Per row of modes (B, R) (-1 = no mode): the entropy in bits of the distribution of the row's modes over
    the rollouts that took one; 0 for a row with at most one such rollout."""
    modes = np.atleast_2d(np.asarray(modes, dtype=int))
    counts = np.stack([(modes == i).sum(axis=1) for i in range(n_modes)], axis=1).astype(float)
    total = counts.sum(axis=1, keepdims=True)
    p = np.divide(counts, total, out=np.zeros_like(counts), where=total > 0)
    return np.where(p > 0, -p * np.log2(np.where(p > 0, p, 1.0)), 0.0).sum(axis=1)  # 0 log 0 = 0, no warning


def every_mode(modes: np.ndarray, n_modes: int) -> np.ndarray:
    """Per row of modes (B, R): True where every one of the n_modes modes occurred."""
    modes = np.atleast_2d(np.asarray(modes, dtype=int))
    return np.all(np.stack([(modes == i).any(axis=1) for i in range(n_modes)], axis=1), axis=1)


def mode_metrics(task: str, names: tuple[str, ...], modes: np.ndarray) -> dict[str, float]:
    """The `E/modes_*` metrics of modes (B, R) of task E."""
    modes = np.atleast_2d(np.asarray(modes, dtype=int))
    n = len(names)
    out = {f"{task}/modes_repeats": float(modes.shape[1]),
           f"{task}/modes_entropy_bits_mean": float(entropy_bits(modes, n).mean()) if modes.size else math.nan,
           f"{task}/modes_both_share": float(every_mode(modes, n).mean()) if modes.size else math.nan,
           f"{task}/modes_between_share": float((modes < 0).mean()) if modes.size else math.nan}
    out.update({f"{task}/modes_share_{name}": float((modes == i).mean()) if modes.size else math.nan
                for i, name in enumerate(names)})
    return out


def samples(model, feedback: str) -> bool:
    """Whether the model's rollouts draw random numbers (an MDN feeding back a draw)."""
    return bool(getattr(model, "is_mdn", False)) and feedback in SAMPLING_FEEDBACKS


def repeat_rollouts(model, task, episodes: list, results0: list[dict[str, Any]], gen_kwargs: dict[str, Any],
                    repeats: int) -> dict[str, Any]:
    """Modes and successes (B, R) of each episode rolled out `repeats` times: repeat 0 is results0 (the ordinary
    evaluation's), repeats 1.. are generated with repeat_seed and evaluated in the task's physics. A model
    that does not sample is rolled once (results0) and counted `repeats` times. Returns the mode_table dict."""
    from stm.rollout import evaluate, generate

    if repeats < 1:
        raise ValueError(f"mode repeats must be >= 1, got {repeats}")
    names = task_modes(task)
    if not names:
        raise ValueError(f"task {task.name!r} defines no modes")
    train_seed = int(gen_kwargs.get("seed", 0))
    deterministic = not samples(model, str(gen_kwargs.get("feedback", "")))
    per_repeat = [results0]
    seeds = [repeat_seed(train_seed, 0)]
    for r in range(1, repeats):
        seeds.append(repeat_seed(train_seed, r))
        if deterministic:
            per_repeat.append(results0)
            continue
        rollouts = generate(model, task, episodes, **{**gen_kwargs, "seed": seeds[-1]})
        per_repeat.append(evaluate(task, rollouts, episodes))
    modes = np.stack([rollout_modes(res, names) for res in per_repeat], axis=1)
    success = np.stack([[float(x.get("success", math.nan)) for x in res] for res in per_repeat], axis=1)
    return mode_table(task.name, names, modes, success, seeds, deterministic)


def mode_table(task: str, names: tuple[str, ...], modes: np.ndarray, success: np.ndarray, seeds: list[int],
               deterministic: bool) -> dict[str, Any]:
    """The `rollouts/modes/<task>.json` artifact: per episode (row) and repeat (column) the mode index (-1 none)
    and success (0/1), each repeat's sampling seed, and per episode its entropy (bits) and whether every
    mode occurred."""
    n = len(names)
    return {"task": task, "modes": list(names), "repeats": int(modes.shape[1]), "deterministic": bool(deterministic),
            "sampling_seeds": [int(s) for s in seeds], "mode": np.asarray(modes, dtype=int).tolist(),
            "success": [[None if math.isnan(v) else int(v >= 0.5) for v in row] for row in np.asarray(success)],
            "entropy_bits": [round(float(v), 6) for v in entropy_bits(modes, n)],
            "every_mode": [bool(v) for v in every_mode(modes, n)]}


def write_mode_tables(details: list, roll_dir) -> None:
    """Each evaluation detail's mode table (TaskEvaluation.modes) as roll_dir/modes/<task>.json."""
    import json
    from pathlib import Path

    from envs.fileio import atomic_write_text

    for d in details:
        if getattr(d, "modes", None) is not None:
            out = Path(roll_dir) / "modes"
            out.mkdir(parents=True, exist_ok=True)
            atomic_write_text(out / f"{d.task}.json", json.dumps(d.modes, sort_keys=True) + "\n")
