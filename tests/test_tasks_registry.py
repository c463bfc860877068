"""The task registry and the Task API that experiments/ and reports/ use instead of task names."""

from __future__ import annotations

import ast
import pkgutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import envs.tasks
from envs.tasks import (
    TASKS,
    Task,
    UnknownTaskError,
    evaluation_tasks,
    get_task,
    model_task_of,
    register,
    task_class,
    task_names,
    tasks_with_panel,
    training_tasks,
)
from envs.tasks.base import StateLayout

TASKS_DIR = Path(envs.tasks.__file__).parent
PANELS = {"tip_paths", "changing_goal", "circles"}


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module:
            out.add(node.module)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
    return out


def test_every_module_of_the_folder_is_discovered_without_an_import_line():
    modules = {m.name for m in pkgutil.iter_modules([str(TASKS_DIR)])}
    assert {f"envs.tasks.{m}" for m in modules} <= set(sys.modules)
    assert {"envs.tasks.circle", "envs.tasks.reacher", "envs.tasks.pickplace", "envs.tasks.stack",
            "envs.tasks.pickplace_changing_goal"} <= {cls.__module__ for cls in TASKS.values()}
    # the package does not name its task modules; base and registry do not import the package, nor base the
    # registry (the task modules import both: no cycle, not even one that only a type checker follows)
    init = _imports(TASKS_DIR / "__init__.py")
    assert not any(m.startswith(("envs.tasks.reacher", "envs.tasks.circle", "envs.tasks.pick")) for m in init)
    assert "envs.tasks" not in _imports(TASKS_DIR / "base.py") | _imports(TASKS_DIR / "registry.py")
    assert not any(m.startswith("envs.tasks.") for m in _imports(TASKS_DIR / "base.py"))


@pytest.mark.slow
@pytest.mark.parametrize("first", ["envs.tasks.base", "envs.tasks.registry", "envs.tasks.stack", "envs.datasets"])
def test_any_module_imports_first_in_a_fresh_process(first):
    code = f"import {first}; from envs.tasks import TASKS; print(len(TASKS))"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert int(proc.stdout.split()[-1]) == len(TASKS)


def test_a_task_in_any_module_registers_and_a_taken_name_is_refused():
    class Toy(Task):
        """A toy for this test."""

        name = "test-toy-task"
        layout = StateLayout(phi_dim=3, psi_dim=3)

    try:
        register(Toy)
        assert task_class("test-toy-task") is Toy and Toy.label == "test-toy-task"
        assert model_task_of("test-toy-task") == "test-toy-task" and "test-toy-task" in training_tasks()
        order = task_names()  # default report_rank: after the built-in tasks
        assert order.index("test-toy-task") > order.index("pick-place-changing-goal")
        register(Toy)  # the same class again (a module reload) is fine

        class Impostor(Toy):
            name = "test-toy-task"

        with pytest.raises(ValueError, match="taken"):
            register(Impostor)
    finally:
        TASKS.pop("test-toy-task", None)


def test_unknown_task_is_one_line_listing_the_known_ones():
    with pytest.raises(UnknownTaskError) as exc:
        get_task("nope")
    assert "unknown task 'nope'" in str(exc.value) and "reacher" in str(exc.value) and "\n" not in str(exc.value)


def test_registry_queries():
    assert task_names()[:3] == ["circle", "reacher", "reacher-changing-goal"]
    assert {"circle", "pick-place", "reacher"} <= set(training_tasks()) and training_tasks() == sorted(training_tasks())
    assert "stack" not in training_tasks()
    assert evaluation_tasks("pick-place") == ["pick-place", "pick-place-changing-goal", "stack"]
    assert model_task_of("stack") == "pick-place"
    assert tasks_with_panel("changing_goal") == ["reacher-changing-goal", "pick-place-changing-goal"]
    assert tasks_with_panel("circles") == ["circle"]


@pytest.mark.parametrize("name", sorted(TASKS))
def test_every_task_declares_what_reports_need(name):
    cls = task_class(name)
    assert cls.label and set(cls.panels) <= PANELS
    assert isinstance(cls.primary_metric, str) and cls.primary_metric
    metrics = {f"{name}/success_rate": 0.75, f"{name}/{cls.primary_metric}_mean": 0.012}
    task = cls.for_evaluation({}, {})
    assert task.sweep_objective("failure_rate", metrics) == pytest.approx(0.25)
    assert task.sweep_objective("final_distance", metrics) == pytest.approx(0.012)
    with pytest.raises(ValueError, match="objective"):
        task.sweep_objective("val", metrics)


def test_labels_and_primary_metrics_of_the_built_in_tasks():
    labels = {n: task_class(n).label for n in ("reacher", "pick-place", "stack", "reacher-changing-goal")}
    assert labels == {"reacher": "reacher", "pick-place": "pick-and-place", "stack": "stacking",
                      "reacher-changing-goal": "changing-goal reacher"}
    assert task_class("circle").primary_metric == "radial_rmse"
    assert task_class("reacher").primary_metric == "final_distance"
    assert task_class("pick-place").block_size == pytest.approx(0.04) and task_class("reacher").block_size is None


@pytest.mark.parametrize("name", ["reacher", "reacher-changing-goal", "pick-place", "stack",
                                  "pick-place-changing-goal"])
def test_random_tasks_give_each_seed_its_own_episodes(name):
    task = get_task(name)
    a, b, a2 = task.episodes(3, 10_000), task.episodes(3, 10_001), task.episodes(3, 10_000)
    assert all(np.array_equal(x.q0, y.q0) and np.array_equal(x.psi, y.psi) for x, y in zip(a, a2, strict=True))
    assert all(not np.allclose(x.q0, y.q0) for x, y in zip(a, b, strict=True))


def test_evaluation_tasks_take_the_trained_tasks_options_they_accept():
    cg = task_class("reacher-changing-goal").for_evaluation({"n_demos": 90, "start_joint_range": 0.2}, {})
    assert cg.n_demos == 45 and cg.start_joint_range == 0.2  # the start range shapes episodes, n_demos does not
    stack = task_class("stack").for_evaluation({"retreat_starts": 0.5, "max_steps": 168}, {})
    assert stack.retreat_starts == 0.0 and stack.max_steps == 168  # a training-data lever stays out
    circle = task_class("circle").for_evaluation({"radii": (0.1, 0.2)}, {"circle_radii": [0.05], "rollouts": 3})
    assert circle.eval_radii == (0.05,) and circle.radii == task_class("circle")().radii


def test_no_package_outside_envs_compares_a_task_name():
    root = TASKS_DIR.parent.parent
    found = set()
    for pkg in ("experiments", "reports", "stm"):
        for path in sorted((root / pkg).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Compare):
                    consts = {n.value for n in ast.walk(node) if isinstance(n, ast.Constant)}
                    if consts & set(TASKS):
                        found.add((str(path.relative_to(root)), ast.unparse(node)))
    assert not found, sorted(found)
