"""The step kernel is a route, not a setting: it leaves a cell's config hash alone (a cell may resume on the
other route, and the default's change from python to auto changed no hash), and each run records which commits and
kernels trained it, from which iteration on: the kernel that ran, not the one asked for."""

from __future__ import annotations

from mlflow.tracking import MlflowClient

from experiments.cell_run import TRAINED_ON, trained_on
from experiments.cells import build_cells
from experiments.runtime.tracking import git_commit
from experiments.study_config import load_profile
from stm.config import TrainConfig
from stm.cpp_ext import step_kernel


def test_trained_on_appends_a_stretch_only_when_the_route_changes():
    first = trained_on("", 0, "abc", "python")
    assert first == "abc:python@0"
    assert trained_on(first, 4000, "abc", "python") == first  # a resume on the same route
    second = trained_on(first, 4000, "def", "python")
    assert second == "abc:python@0;def:python@4000"
    third = trained_on(second, 9000, "def", "cpp")
    assert third == "abc:python@0;def:python@4000;def:cpp@9000"
    assert trained_on(third, 9500, "abc", "python") == third + ";abc:python@9500"  # back to an earlier route


def test_the_step_kernel_is_not_hashed_but_other_settings_are():
    base = {c.key: c.config_hash for c in build_cells(load_profile("smoke"))}
    assert all(c.train.step_kernel == "auto" for c in build_cells(load_profile("smoke")))  # the default
    for kernel in ("cpp", "python"):
        cells = build_cells(load_profile("smoke", [f"train.step_kernel={kernel}"]))
        assert {c.key: c.config_hash for c in cells} == base
        assert all(c.train.step_kernel == kernel for c in cells)
    assert TrainConfig().hashed_dict() == TrainConfig(step_kernel="python").hashed_dict()
    assert "step_kernel" not in TrainConfig(step_kernel="cpp").hashed_dict()
    for override in ("train.step_kernel=cpp", "per_task.reacher.train.step_kernel=cpp", "train.step_kernel=python"):
        cfg = load_profile("smoke", [override])
        assert cfg.study_hash() == load_profile("smoke").study_hash()
        assert cfg.resolved_study_name() == load_profile("smoke").resolved_study_name()  # a re-run continues it
    bf16 = build_cells(load_profile("smoke", ["train.matmul_dtype=bfloat16"]))
    assert {c.key: c.config_hash for c in bf16} != base  # a different result: hashed


def test_each_run_records_its_kernel_and_route(smoke_store):
    client = MlflowClient(smoke_store.uri)
    exp = client.get_experiment_by_name("ablation")
    cells = client.search_runs([exp.experiment_id], "tags.role = 'cell'")
    assert cells
    for run in cells:
        assert run.data.params["train.step_kernel"] == "auto"  # asked for
        stretches = run.data.tags[TRAINED_ON].split(";")
        assert stretches[0] == f"{git_commit()}:{step_kernel('auto')}@0"  # ran: cpp where the extension builds
