"""One ablation cell in one process: train (resuming from the run's checkpoint artifact if there is one; else, asked,
from its kept weights: experiments/weights_resume.py), evaluate on every task the model serves, log everything to the
cell's MLflow child run through MlflowClient. Runs in the main process (1 worker) or in a spawned worker.

`CellRun` is what a cell's run needs around its training, shared with experiments/pack.py
(a cell group's seeds trained together): `start` (RUNNING, params, config artifact, the
checkpoint to resume from, the metric buffer), the training callbacks, `evaluate` (metrics,
rollouts, figures), then `finished` or `failed`."""

from __future__ import annotations

import json
import logging
import os
import random
import re
import tempfile
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from experiments.cells import Cell
from experiments.runtime.tracking import (
    Client,
    MetricBuffer,
    flatten,
    git_commit,
    last_logged_step,
    log_metrics,
    log_params,
    provenance_params,
    set_tags,
)

log = logging.getLogger(__name__)

CHECKPOINT_NAME = "model.pt"
CHECKPOINT_DIR = "checkpoint"
KEPT_CHECKPOINT_DIR = "checkpoint_at"  # checkpoint_at/<iteration>/model.pt: copies kept by Cell.keep_checkpoints
# weights_at/<iteration>/weights.pt: a model's weights alone (stm.training.weights), as an imported study export
# that carries models brings them (reports.data.export --with-models); the milestones verb evaluates them
WEIGHTS_DIR = "weights_at"
WEIGHTS_NAME = "weights.pt"
# Test hooks (never set in normal use): once a checkpoint is in the store, append "<run_id> <iteration>"
# to the file named by SIGNAL_FILE_ENV, and with HOLD_ENV=1 then wait there until killed or interrupted,
# so a fault test kills or interrupts a cell at a known point instead of racing its training.
SIGNAL_FILE_ENV = "ACRMDN_TEST_SIGNAL_FILE"
HOLD_ENV = "ACRMDN_TEST_HOLD"


@dataclass
class CellResult:
    key: str
    run_id: str
    status: str  # FINISHED | FAILED
    error: str = ""
    metrics: dict[str, float] = field(default_factory=dict)
    seconds: float = 0.0
    resumed_from: int = 0
    # a store fault (experiments/runtime/store_faults.py) stopped the cell: nothing more was written, its run stays
    # resumable, and the study stops
    store_fault: str = ""


def seed_everything(seed: int) -> None:
    import numpy as np
    import torch

    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def fetch_checkpoint(client: Client, run_id: str, dst: Path) -> Path | None:
    """Download the run's last checkpoint artifact, if it has one."""
    names = {Path(f.path).name for f in client.list_artifacts(run_id, CHECKPOINT_DIR)}
    if CHECKPOINT_NAME not in names:
        return None
    local = client.download_artifacts(run_id, f"{CHECKPOINT_DIR}/{CHECKPOINT_NAME}", str(dst))
    return Path(local)


def cell_params(cell: Cell) -> dict[str, str]:
    """The run's params: the hashed config, the product dtype (also at its default) and the device it trains on
    (resolved: a bad or missing device fails the cell here, with one line)."""
    from stm.device import resolve_device

    return {**flatten(cell.resolved), "train.matmul_dtype": cell.train.matmul_dtype,
            "train.step_kernel": cell.train.step_kernel, "device": str(resolve_device(cell.device)),
            "profile": cell.profile, "study_name": cell.study_name, **provenance_params()}


TRAINED_ON = "trained_on"


def trained_on(previous: str, iteration: int, commit: str, step_kernel: str) -> str:
    """The run's tag `trained_on`: `commit:step_kernel@iteration` for each stretch of training that started on
    another commit or step kernel than the one before (a resumed run may go on with newer code), `;`-separated."""
    route = f"{commit}:{step_kernel}"
    entries = [e for e in previous.split(";") if e]
    if entries and entries[-1].rsplit("@", 1)[0] == route:
        return previous
    return ";".join([*entries, f"{route}@{iteration}"])


def setup_process(log_level: int, threads: int | None) -> None:
    """Logging and torch threads of a worker process (`threads`: so that K workers do not
    oversubscribe the cores)."""
    logging.basicConfig(level=log_level, format="%(asctime)s %(processName)s %(name)s: %(message)s")
    quiet_store_errors(log_level)
    if threads:
        import torch

        torch.set_num_threads(threads)


def quiet_store_errors(log_level: int) -> None:
    """MLflow logs every SQL error with its traceback before raising it, which the caller reports in one line
    (a store fault: experiments/runtime/store_faults.py): the traceback only with debug logging."""
    logging.getLogger("mlflow.store.db.utils").setLevel(logging.DEBUG if log_level <= logging.DEBUG
                                                        else logging.CRITICAL)


def as_cell(cell: Cell | dict[str, Any]) -> Cell:
    return cell if isinstance(cell, Cell) else Cell.from_dict(cell)


def load_task(cell: Cell):
    """The cell's training task and its (cached) demonstrations."""
    from envs.datasets import load_demos
    from envs.tasks import get_task

    task = get_task(cell.task, **cell.data)
    return task, load_demos(task, seed=cell.dataset_seed)


def run_cell(cell: Cell | dict[str, Any], uri: str, run_id: str, progress: bool = False,
             log_level: int = logging.INFO, threads: int | None = None) -> CellResult:
    """Entry point for worker processes: the cell (it pickles under spawn; or its to_dict, plain
    data) with its typed configs."""
    from stm.training.loop import train

    setup_process(log_level, threads)
    cell = as_cell(cell)
    client = Client(uri, create=False)
    start = time.perf_counter()
    run = CellRun(cell, client, run_id)
    try:
        with tempfile.TemporaryDirectory(prefix="acrmdn-cell-") as tmp:
            run.start(Path(tmp))
            task, demos = load_task(cell)
            run.check_checkpoint(task)
            seed_everything(cell.seed)
            log.info("cell %s: training %d iterations (from %d)", cell.key, cell.train.iters, run.resumed_from)
            result = train(cell.model, cell.train, task, demos, checkpoint_path=run.ckpt_path, resume=True,
                           on_metrics=run.buffer.add, on_checkpoint=run.on_checkpoint,
                           on_validation=run.on_validation, progress=progress, device=cell.device)
            metrics = run.evaluate(result)
        return run.finished(metrics, start)
    except KeyboardInterrupt:  # Ctrl-C: KILLED, resumable from its checkpoint (taken where it stood)
        mark_killed(client, [run_id])
        raise
    except Exception as exc:
        return run.failed(exc, start)


def test_signal(marks: list[tuple[str, int]]) -> None:
    """The fault tests' hook (see SIGNAL_FILE_ENV) for checkpoints (run_id, iteration); a no-op
    unless the variable is set. A pack signals its seeds' checkpoints of one iteration at once."""
    path = os.environ.get(SIGNAL_FILE_ENV)
    if not path:
        return
    with open(path, "a") as f:  # one short O_APPEND write: lines from parallel workers do not interleave
        f.write("".join(f"{run_id} {iteration}\n" for run_id, iteration in marks))
    while os.environ.get(HOLD_ENV) == "1":  # until SIGKILL, or Ctrl-C raising KeyboardInterrupt here
        time.sleep(3600)


def mark_killed(client: Client, run_ids: list[str]) -> None:
    """Interrupted cells: RUNNING runs become KILLED (a re-run resumes them from their checkpoint)."""
    for run_id in run_ids:
        try:
            if client.get_run(run_id).info.status == "RUNNING":
                set_tags(client, run_id, {"error": "interrupted (Ctrl-C); re-run the study to resume"})
                client.set_terminated(run_id, "KILLED")
        except Exception:  # best effort on the way out; the run stays resumable either way
            log.warning("could not mark run %s KILLED", run_id)


class CheckpointMismatch(ValueError):
    """A cell's checkpoint artifact trained with another config; str() names the command that discards it."""


def _mismatch(exc: ValueError, ckpt: dict, cell: Cell) -> str:
    """What stm.training.checkpoint.check_resumable refused, in a few words (its message holds whole configs)."""
    text = str(exc)
    if "another model config" in text:
        saved, now = ckpt.get("model_config", {}), cell.model.to_dict()
        differ = sorted(k for k in {**saved, **now} if saved.get(k) != now.get(k))
        return f"was trained with another model config (differing in {', '.join(differ)})"
    if "state layout" in text:
        return "was trained on another state layout"
    settings = re.search(r"with other settings \(([^)]*)\)", text)
    if settings:
        return f"was trained with other training settings (differing in {settings.group(1)})"
    return f"does not fit this cell ({text.splitlines()[0][:200]})"


def discard_command(run_id: str) -> str:
    """The command that discards a cell's run, checkpoint included (a re-run of the study then trains the cell
    from scratch in a new run); the store named as the user's environment names it, never by a path."""
    from experiments.runtime.tracking import DEFAULT_TRACKING_URI

    uri = os.environ.get("MLFLOW_TRACKING_URI", "").strip()
    env = "" if uri else f"MLFLOW_TRACKING_URI={DEFAULT_TRACKING_URI} "  # the mlflow CLI's own default is ./mlruns
    return f"`{env}mlflow runs delete --run-id {run_id}`"


class CellRun:
    """One cell's MLflow run around its training (see the module docstring)."""

    def __init__(self, cell: Cell, client: Client, run_id: str):
        self.cell, self.client, self.run_id = cell, client, run_id
        self.resumed_from = 0
        self.from_weights = False  # resuming from kept weights (experiments/weights_resume.py), not a checkpoint
        self.work: Path | None = None
        self.ckpt_path: Path | None = None
        self.buffer: MetricBuffer | None = None

    def start(self, work: Path) -> None:
        """RUNNING, params, the config artifact, the checkpoint to resume from (in `work`) and the
        metric buffer."""
        from stm.training.checkpoint import CheckpointError, load_checkpoint

        cell, client, run_id = self.cell, self.client, self.run_id
        client.update_run(run_id, status="RUNNING")
        log_params(client, run_id, cell_params(cell))
        self.work = work
        config_file = work / "config" / "config.json"
        config_file.parent.mkdir(parents=True)
        config_file.write_text(json.dumps(cell.resolved, indent=2, sort_keys=True))
        client.log_artifact(run_id, str(config_file), "config")

        ckpt_dir = work / "ckpt"
        ckpt_dir.mkdir()
        self.ckpt_path = ckpt_dir / CHECKPOINT_NAME
        fetched = fetch_checkpoint(client, run_id, work / "download")
        if fetched is not None:
            fetched.replace(self.ckpt_path)
            try:
                self.resumed_from = int(load_checkpoint(self.ckpt_path)["iteration"])
            except CheckpointError as exc:  # truncated, corrupt or another format version: start over
                log.warning("cell %s: checkpoint artifact unusable (%s); retraining from scratch", cell.key, exc)
                self.ckpt_path.unlink()
                set_tags(client, run_id, {"checkpoint_discarded": str(exc)[:500]})
            else:
                log.info("cell %s resumes from its checkpoint at iteration %d", cell.key, self.resumed_from)
                set_tags(client, run_id, {"resumed_from_iteration": self.resumed_from})
        else:
            from experiments.weights_resume import prepare_from_weights

            at = prepare_from_weights(client, run_id, cell, self.ckpt_path, work / "weights")
            self.resumed_from, self.from_weights = at or 0, at is not None
        previous = client.get_run(run_id).data.tags.get(TRAINED_ON, "")
        from stm.cpp_ext import step_kernel
        from stm.device import resolve_device

        ran = step_kernel(cell.train.step_kernel, resolve_device(cell.device).type)  # the kernel that runs, not asked
        route = trained_on(previous, self.resumed_from, git_commit(), ran)
        if route != previous:
            set_tags(client, run_id, {TRAINED_ON: route})
        # a resumed run recomputes the steps after its checkpoint exactly: drop the ones already logged
        # (a retrain from scratch recomputes the same values too: the seed is the cell's). One resumed from kept
        # weights computes other values after them, yet the ones already logged stay: a step is logged once
        logged = last_logged_step(client, run_id, ("train/loss", "val/metric")) \
            if fetched is not None or self.from_weights else -1
        self.buffer = MetricBuffer(client, run_id, skip_through=logged)

    def check_checkpoint(self, task) -> None:
        """The checkpoint to resume from belongs to this cell's config (model, state layout, training settings),
        else CheckpointMismatch: the cell fails before training, naming the command that discards it."""
        from stm.training.checkpoint import check_resumable, load_checkpoint

        if self.ckpt_path is None or not self.ckpt_path.is_file():
            return
        ckpt = load_checkpoint(self.ckpt_path)
        try:
            check_resumable(ckpt, self.cell.model, self.cell.train, task, self.ckpt_path)
        except ValueError as exc:
            if self.from_weights:
                raise CheckpointMismatch(f"the {WEIGHTS_DIR}/{self.resumed_from}/{WEIGHTS_NAME} artifact of run "
                                         f"{self.run_id} {_mismatch(exc, ckpt, self.cell)} (another cell's?); to "
                                         "train this cell from scratch, re-run without --resume-from-weights") from None
            raise CheckpointMismatch(f"the checkpoint artifact of run {self.run_id} {_mismatch(exc, ckpt, self.cell)} "
                                     f"(another cell's?); to discard it and train this cell from scratch: "
                                     f"{discard_command(self.run_id)}, then re-run the study") from None
        if self.from_weights:
            from experiments.weights_resume import mark_resumed

            mark_resumed(self.client, self.run_id, self.cell, self.resumed_from)

    def on_checkpoint(self, path: Path, iteration: int, signal: bool = True) -> None:
        """The checkpoint into the store; then the fault tests' hook unless `signal` is False
        (a pack signals its seeds together). A store file that disappeared stops the cell here (StoreFault)."""
        self.client.check_store()
        self.buffer.flush()
        self.client.log_artifact(self.run_id, str(path), CHECKPOINT_DIR)
        every = self.cell.keep_checkpoints
        if every and iteration % every == 0:
            self.client.log_artifact(self.run_id, str(path), f"{KEPT_CHECKPOINT_DIR}/{iteration}")
        set_tags(self.client, self.run_id, {"checkpoint_iteration": iteration})
        if signal:
            test_signal([(self.run_id, iteration)])

    def on_validation(self, iteration: int, value: float) -> bool:
        self.buffer.add(iteration, {"val/metric": value})
        return False

    def evaluate(self, result) -> dict[str, float]:
        """Log the training result (a stm.training.loop.TrainResult), evaluate the model on every task it
        serves and log the metrics, rollouts and figures."""
        import numpy as np

        from experiments.evaluation import evaluate_model, rollout_arrays, rollout_figure
        from experiments.mode_repeats import write_mode_tables
        from experiments.model_logging import log_stm  # the trained STM as the run's MLflow model "model"
        from stm.device import resolve_device

        cell, client, run_id, work = self.cell, self.client, self.run_id, self.work
        self.buffer.flush()
        log_stm(result.model, client, run_id)
        log.info("cell %s: trained in %.0fs; evaluating on %s", cell.key, result.seconds, ", ".join(cell.eval_tasks))
        log_metrics(client, run_id, {"time/train_seconds": result.seconds, "train/iterations": result.iterations})
        train_cfg = cell.train
        metrics, details = evaluate_model(result.model.to(resolve_device(cell.device)), list(cell.eval_tasks),
                                          cell.eval_dict(), seed=cell.seed,
                                          phi_mode=train_cfg.phi_mode, data=cell.data,
                                          train_feedback=train_cfg.feedback, temperature=train_cfg.temperature)
        log_metrics(client, run_id, metrics)
        metrics["time/train_seconds"] = result.seconds  # in the run since training ended (above): once
        n_fig = cell.eval.figures
        roll_dir = work / "rollouts"
        roll_dir.mkdir()
        timing = {}
        for d in details:  # per-episode paths and outcomes for the report's trajectory figures
            np.savez_compressed(roll_dir / f"{d.task}.npz", **rollout_arrays(d, n_expert=n_fig))
            timing[d.task] = d.timing
        write_mode_tables(details, roll_dir)  # rollouts/modes/<task>.json where eval.mode_repeats measured them
        (roll_dir / "ik_timing.json").write_text(json.dumps(timing, indent=2))
        client.log_artifacts(run_id, str(roll_dir), "rollouts")
        if n_fig:
            fig_dir = work / "figures"
            for d in details:
                rollout_figure(d, fig_dir / f"{d.task}_rollouts.png", n_fig)
            client.log_artifacts(run_id, str(fig_dir), "figures")
        return metrics

    def finished(self, metrics: dict[str, float], start: float) -> CellResult:
        set_tags(self.client, self.run_id, {"error": ""})
        self.client.set_terminated(self.run_id, "FINISHED")
        return CellResult(self.cell.key, self.run_id, "FINISHED", metrics=metrics,
                          seconds=time.perf_counter() - start, resumed_from=self.resumed_from)

    def failed(self, exc: BaseException, start: float) -> CellResult:
        """FAILED with its reason (an exception raised, or a stm.training.loop.TrainingDiverged reported). A store
        fault writes nothing more: the run stays as it is, resumable from its last checkpoint artifact."""
        from experiments.runtime.store_faults import fault_reason

        reason = fault_reason(exc)
        if reason is not None:
            log.warning("cell %s stopped: the store failed (%s); its run stays resumable", self.cell.key, reason)
            return CellResult(self.cell.key, self.run_id, "FAILED", error=f"store fault: {reason}",
                              seconds=time.perf_counter() - start, resumed_from=self.resumed_from, store_fault=reason)
        text = f"{type(exc).__name__}: {exc}"
        log.error("cell %s failed: %s", self.cell.key, text)
        trace = "".join(traceback.format_exception(exc))[-4000:]
        try:
            set_tags(self.client, self.run_id, {"error": text, "mlflow.note.content":
                                                f"FAILED: {text}\n\n```\n{trace}\n```"})
            self.client.set_terminated(self.run_id, "FAILED")
        except Exception:  # the store itself is unreachable: the summary still reports the failure
            log.exception("could not mark run %s FAILED", self.run_id)
        return CellResult(self.cell.key, self.run_id, "FAILED", error=text.splitlines()[0][:500],
                          seconds=time.perf_counter() - start, resumed_from=self.resumed_from)
