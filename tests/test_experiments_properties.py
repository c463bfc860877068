"""Property tests (hypothesis) over config values and CLI arguments: every rejected input
exits 2 with one line naming the field, no traceback, and leaves the store untouched; every
accepted value round-trips through the params logged to a real MLflow run."""

from __future__ import annotations

import tempfile
from pathlib import Path

import pytest
from cli_helpers import run_in_process
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from experiments.study_config import OBJECTIVES, SAMPLERS, ConfigError, parse_override
from stm.config import FEEDBACKS, HEADS, PHI_MODES

# integer fields and the smallest allowed value
INT_FIELDS = {"train.iters": 1, "train.batch_size": 1, "train.u": 1, "train.v": 0, "train.val_episodes": 1,
              "model.hidden_size": 1, "model.num_layers": 1, "model.mixtures": 1, "eval.rollouts": 1,
              "eval.figures": 0, "seeds": 1, "workers": 0, "sweep.trials": 1, "sweep.heartbeat": 1}
CHOICES = {"train.feedback": FEEDBACKS, "eval.feedback": FEEDBACKS, "model.head": HEADS,
           "train.phi_mode": PHI_MODES, "sweep.sampler": SAMPLERS, "sweep.objective": OBJECTIVES}
SECTIONS = ("train", "model", "eval", "sweep")
KNOWN = set(INT_FIELDS) | set(CHOICES)
words = st.text(alphabet=st.characters(codec="utf-8", exclude_categories=("Cs",)), min_size=1, max_size=20)


def _value(text: str):
    return parse_override(f"x={text}")[1]


def _not_int(text: str) -> bool:
    v = _value(text)
    return isinstance(v, bool) or not isinstance(v, int)


too_small = st.sampled_from(sorted(INT_FIELDS.items())).flatmap(
    lambda kv: st.integers(min_value=-10**9, max_value=kv[1] - 1).map(lambda v: (f"{kv[0]}={v}", kv[0])))
not_an_int = st.tuples(st.sampled_from(sorted(INT_FIELDS)), words.filter(lambda t: "=" not in t and _not_int(t))
                       ).map(lambda fv: (f"{fv[0]}={fv[1]}", fv[0]))
not_a_choice = st.sampled_from(sorted(CHOICES.items())).flatmap(
    lambda kv: words.filter(lambda t: _value(t) not in kv[1]).map(lambda t: (f"{kv[0]}={t}", kv[0])))
unknown_field = st.tuples(st.sampled_from(SECTIONS), st.from_regex(r"[a-z][a-z_\n\r\t ]{0,12}", fullmatch=True)).filter(
    lambda sf: f"{sf[0]}.{sf[1].strip()}" not in KNOWN and sf[1].strip() not in _fields(sf[0])).map(
    lambda sf: (f"{sf[0]}.{sf[1]}=1", f"{sf[0]}.{sf[1].strip()}".replace("\r", "\\r").replace("\n", "\\n")))


def _fields(section: str) -> set[str]:
    import dataclasses

    from experiments.study_config import EvalConfig, SweepConfig
    from stm.config import ModelConfig, TrainConfig

    cls = {"train": TrainConfig, "model": ModelConfig, "eval": EvalConfig, "sweep": SweepConfig}[section]
    return {f.name for f in dataclasses.fields(cls)}


@pytest.fixture(scope="module")
def store_dir():
    """A working directory with an existing (empty) store file that must stay untouched."""
    with tempfile.TemporaryDirectory(prefix="acrmdn-prop-") as d:
        (Path(d) / "mlflow.db").write_bytes(b"")
        yield Path(d)


def _run_cli(argv: list[str], cwd: Path) -> tuple[int, str]:
    return run_in_process("experiments", argv, cwd)


def _assert_rejected(argv: list[str], field: str, cwd: Path) -> None:
    before = sorted(p.name for p in cwd.iterdir())
    code, err = _run_cli(argv, cwd)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2, (argv, err)
    assert "Traceback" not in err
    errors = [ln for ln in lines if ln.startswith("error:")]
    assert len(errors) == 1, err
    assert field in errors[0], (field, errors[0])
    assert sorted(p.name for p in cwd.iterdir()) == before and (cwd / "mlflow.db").read_bytes() == b""


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(bad=st.one_of(too_small, not_an_int, not_a_choice, unknown_field),
       command=st.sampled_from(["ablation", "sweep"]))
@pytest.mark.slow
def test_rejected_set_values_exit_2_with_one_line_naming_the_field(store_dir, monkeypatch, bad, command):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    override, field = bad
    _assert_rejected([command, "--profile", "smoke", "--set", override], field, store_dir)


cli_bad = st.one_of(
    st.tuples(st.just("--seeds"), st.integers(max_value=0).map(str), st.just("seeds")),
    st.tuples(st.just("--seeds"), words.filter(lambda t: not t.strip().lstrip("-").isdigit() and
                                                not t.startswith("-")), st.just("--seeds")),
    st.tuples(st.just("--workers"), st.integers(max_value=-1).map(str), st.just("workers")),
    st.tuples(st.just("--tasks"), st.from_regex(r"[a-z]{3,10}", fullmatch=True).filter(
        lambda t: t not in {"reacher", "circle"} and "pick" not in t), st.just("tasks")),
    st.tuples(st.just("--variants"), st.from_regex(r"[a-z]{3,10}", fullmatch=True).filter(
        lambda t: t not in {"lstm"}), st.just("variants")),
    st.tuples(st.just("--profile"), st.from_regex(r"[a-z]{3,10}", fullmatch=True).filter(
        lambda t: t not in {"smoke", "quick", "paper"}), st.just("profile")),
)


@pytest.mark.slow
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(bad=cli_bad)
def test_rejected_cli_arguments_exit_2_with_one_line_naming_the_field(store_dir, monkeypatch, bad):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    flag, value, field = bad
    argv = ["ablation", "--profile", "smoke", flag, value] if flag != "--profile" else ["ablation", flag, value]
    _assert_rejected(argv, field, store_dir)


# fields that no variant rewrites, with values the config accepts
accepted = st.one_of(
    st.tuples(st.sampled_from(["train.iters", "train.batch_size", "train.val_episodes", "model.hidden_size",
                               "model.num_layers", "eval.rollouts"]), st.integers(min_value=1, max_value=10**6)),
    st.tuples(st.sampled_from(["train.lr", "model.sigma_min"]),
              st.floats(min_value=1e-12, max_value=1e3, allow_nan=False, allow_infinity=False)),
    st.tuples(st.just("train.grad_clip"), st.floats(min_value=0.0, max_value=1e6, allow_nan=False)),
    st.tuples(st.just("eval.feedback"), st.sampled_from(FEEDBACKS)),
)


@pytest.fixture(scope="module")
def mlflow_run(tmp_path_factory):
    from experiments.runtime.tracking import Client, get_or_create_experiment

    uri = f"sqlite:///{tmp_path_factory.mktemp('prop-store') / 'mlflow.db'}"
    client = Client(uri)
    return client, get_or_create_experiment(client, "ablation")


@pytest.mark.slow
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(item=accepted)
def test_accepted_values_round_trip_through_the_logged_params(mlflow_run, item):
    from experiments.cell_run import cell_params
    from experiments.cells import build_cells
    from experiments.runtime.tracking import log_params
    from experiments.study_config import load_profile

    field, value = item
    text = repr(value) if isinstance(value, float) else str(value)
    try:
        cfg = load_profile("smoke", [f"{field}={text}"], variants=["ac-lstm-mdn"])
    except ConfigError as e:  # accepted values only (e.g. a batch larger than the data is fine)
        pytest.fail(f"{field}={text} rejected: {e}")
    client, exp_id = mlflow_run
    run_id = client.create_run(exp_id).info.run_id
    log_params(client, run_id, cell_params(build_cells(cfg)[0]))
    logged = client.get_run(run_id).data.params[field]
    assert _value(logged) == value and type(_value(logged)) is type(value), (field, value, logged)
