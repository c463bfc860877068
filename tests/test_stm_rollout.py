import numpy as np
import pytest
import torch
from stm_toytask import ToyReach, single_torch_thread  # noqa: F401  (autouse)

from envs.kinematics import tip_position_np
from envs.tasks.base import Episode
from stm.config import ModelConfig, TrainConfig
from stm.model import STM
from stm.rollout import FEEDBACKS, evaluate, generate
from stm.training.loop import train
from stm.training.validation import demo_episodes


@pytest.fixture(scope="module")
def overfit():
    """An ac-lstm-mdn trained to overfit a single demonstration (with a gripper channel)."""
    task = ToyReach(n_demos=1, min_steps=12, max_steps=12, gripper=True)
    demos = task.demos(4)
    cfg = TrainConfig(iters=150, batch_size=1, lr=1e-2, u=2, v=2, log_every=0)
    res = train(ModelConfig(hidden_size=32, num_layers=2, mixtures=2), cfg, task, demos)
    return task, demos, res.model


@pytest.mark.slow
def test_rollout_of_an_overfit_model_reproduces_its_demo(overfit):
    task, demos, model = overfit
    episodes = demo_episodes(demos, 1)
    ro = generate(model, task, episodes)
    L = int(demos.lengths[0])
    assert ro.q.shape == (1, L + 1, 7) and ro.grip.shape == (1, L + 1) and ro.seconds > 0
    tip_err = np.linalg.norm(tip_position_np(ro.q[0]) - tip_position_np(demos.q[0, : L + 1]), axis=-1)
    assert tip_err.max() < 0.01, tip_err  # within 1 cm along the whole path
    assert np.array_equal(ro.grip[0, 1:], demos.grip[0, 1: L + 1])  # the gripper closes on the same step


def test_batched_episodes_of_different_horizons_match_single_runs(overfit):
    task, demos, model = overfit
    base = demo_episodes(demos, 1)[0]
    eps = [Episode(q0=base.q0, psi=base.psi[:6], horizon=5), base,
           Episode(q0=base.q0 + 0.05, psi=base.psi, horizon=12)]
    ro = generate(model, task, eps)
    assert ro.q.shape == (3, 13, 7) and ro.horizons.tolist() == [5, 12, 12]
    assert np.all(ro.q[0, 6:] == ro.q[0, 5])  # padded with the last valid row
    for i, ep in enumerate(eps):
        single = generate(model, task, [ep])
        np.testing.assert_allclose(ro.q[i, : ep.horizon + 1], single.q[0], atol=1e-5)


def test_goal_switch_changes_the_trajectory_only_after_the_switch(overfit):
    task, demos, model = overfit
    ep = demo_episodes(demos, 1)[0]
    psi = ep.psi.copy()
    psi[6:] += np.array([0.0, 0.15, 0.0])
    switched = Episode(q0=ep.q0, psi=psi, horizon=ep.horizon)
    ro = generate(model, task, [ep, switched])
    np.testing.assert_allclose(ro.q[0, :7], ro.q[1, :7], atol=1e-6)  # step 7 is the first predicted from new psi
    assert np.abs(ro.q[0, 8:] - ro.q[1, 8:]).max() > 1e-3


def test_a_restart_step_continues_as_a_fresh_episode_from_the_current_q(overfit):
    task, demos, model = overfit
    ep = demo_episodes(demos, 1)[0]
    k = 6
    chained = Episode(q0=ep.q0, psi=ep.psi, horizon=ep.horizon, info={"restart_steps": [k]})
    plain, ro = generate(model, task, [ep, chained]).q
    np.testing.assert_allclose(ro[: k + 1], plain[: k + 1], atol=1e-6)  # unchanged up to the restart
    fresh = generate(model, task, [Episode(q0=ro[k], psi=ep.psi[k:], horizon=ep.horizon - k)]).q[0]
    np.testing.assert_allclose(ro[k:], fresh, atol=1e-5)  # then exactly a new episode from q_k
    assert np.abs(ro[k + 1:] - plain[k + 1:]).max() > 1e-4
    with pytest.raises(ValueError, match="restart step 40 outside"):
        generate(model, task, [Episode(q0=ep.q0, psi=ep.psi, horizon=ep.horizon, info={"restart_steps": [40]})])


def test_a_restart_step_with_a_listed_configuration_continues_from_it(overfit):
    """info["restart_q"]: at its restart step the model restarts from that configuration (a task moves the arm
    there by script between the two rows): the row of the restart step keeps where the last segment ended, the rest
    is a fresh episode from the listed configuration; the packed rollout of several models agrees."""
    task, demos, model = overfit
    ep = demo_episodes(demos, 1)[0]
    k, elsewhere = 6, np.asarray(ep.q0) + 0.1
    listed = Episode(q0=ep.q0, psi=ep.psi, horizon=ep.horizon, info={"restart_steps": [k], "restart_q": [elsewhere]})
    chained = Episode(q0=ep.q0, psi=ep.psi, horizon=ep.horizon, info={"restart_steps": [k]})
    ro, plain = generate(model, task, [listed, chained]).q
    np.testing.assert_allclose(ro[: k + 1], plain[: k + 1], atol=1e-6)  # the last segment's end is kept
    fresh = generate(model, task, [Episode(q0=elsewhere, psi=ep.psi[k:], horizon=ep.horizon - k)]).q[0]
    np.testing.assert_allclose(ro[k + 1:], fresh[1:], atol=1e-5)  # then a new episode from the listed configuration
    for packed in generate([model, model], task, [listed]):  # two models: the batched step
        np.testing.assert_allclose(packed.q[0], ro, atol=1e-5)
    with pytest.raises(ValueError, match="2 restart configurations for 1 restart steps"):
        generate(model, task, [Episode(q0=ep.q0, psi=ep.psi, horizon=ep.horizon,
                                       info={"restart_steps": [k], "restart_q": [elsewhere, elsewhere]})])


def test_sampling_is_seeded_and_evaluate_runs_physics(overfit):
    task, demos, model = overfit
    eps = task.episodes(2, seed=0)
    a = generate(model, task, eps, feedback="sample", seed=1)
    b = generate(model, task, eps, feedback="sample", seed=1)
    assert np.array_equal(a.q, b.q)
    # physics against the kinematics: the overfit model reaches its demo's goal, not another episode's
    demo, other = demo_episodes(demos, 1)[0], eps[0]
    other = Episode(q0=demo.q0, psi=other.psi[: demo.horizon + 1], horizon=demo.horizon)
    both = [demo, other]
    ro = generate(model, task, both)
    results = evaluate(task, ro, both)
    fk_distance = [np.linalg.norm(tip_position_np(ro.q[i, -1]) - ep.psi[-1]) for i, ep in enumerate(both)]
    assert fk_distance[0] < 0.02 < 0.1 < fk_distance[1], fk_distance
    assert [r["success"] for r in results] == [1.0, 0.0]
    for r, d in zip(results, fk_distance, strict=True):
        assert r["final_distance"] == pytest.approx(d, abs=0.02), (r, d)  # position control tracks the plan
    with pytest.raises(ValueError, match="rollouts for"):
        evaluate(task, a, eps[:1])


def test_rollout_rejects_a_task_of_another_state_size(overfit):
    _, _, model = overfit
    with pytest.raises(ValueError, match="state size"):
        generate(model, ToyReach(gripper=False), ToyReach(gripper=False).episodes(1, 0))


def _two_mode_model(task, step=0.02):
    """An MDN whose mixture ignores its input: two equally likely components that move joint 0 by
    +step or -step per step (normalisation is the identity)."""
    model = STM(ModelConfig(hidden_size=4, num_layers=1, mixtures=2), task.layout)
    D = task.layout.dim
    with torch.no_grad():
        model.head.weight.zero_()
        bias = torch.zeros_like(model.head.bias)
        bias[4 + 0] = step  # mu_0, dq0
        bias[4 + D] = -step  # mu_1, dq0
        model.head.bias.copy_(bias)
    return model


def test_segment_component_commits_to_one_component_per_segment():
    task = ToyReach(max_steps=10)
    model = _two_mode_model(task)
    eps = task.episodes(24, seed=0)
    ro = generate(model, task, eps, feedback="segment_component", seed=5)
    drift = ro.q[:, -1, 0] - ro.q[:, 0, 0]
    assert np.allclose(np.abs(drift), 0.02 * ro.horizons, atol=1e-4)  # every step in one direction
    assert np.all(ro.components == ro.components[:, :1])  # one component for the whole episode
    assert 6 <= (drift > 0).sum() <= 18  # both components drawn (50/50 weights)
    again = generate(model, task, eps, feedback="segment_component", seed=5)
    assert np.array_equal(ro.q, again.q)  # seeded
    per_step = generate(model, task, eps, feedback="sample_component", seed=5)
    switched = (per_step.components != per_step.components[:, :1]).any(axis=1)
    assert switched.mean() > 0.9  # drawn anew each step, it changes mode within an episode
    top = generate(model, task, eps)  # the default: the most likely (tie: the first) component
    assert np.all(top.components == 0) and np.allclose(top.q[:, -1, 0] - top.q[:, 0, 0], 0.02 * top.horizons)


def test_segment_component_draws_again_at_a_restart_step():
    task = ToyReach(max_steps=12)
    model = _two_mode_model(task)
    base = task.episodes(40, seed=1)
    eps = [Episode(q0=ep.q0, psi=ep.psi, horizon=12, info={"restart_steps": [6]}) for ep in base]
    ro = generate(model, task, eps, feedback="segment_component", seed=2)
    c = ro.components
    assert np.all(c[:, :6] == c[:, :1]) and np.all(c[:, 6:] == c[:, 6:7])  # constant within each segment
    assert (c[:, 0] != c[:, 6]).any() and (c[:, 0] == c[:, 6]).any()  # the second draw is a new one


def test_unknown_feedback_and_bad_temperature_are_errors(overfit):
    task, demos, model = overfit
    eps = demo_episodes(demos, 1)
    with pytest.raises(ValueError, match="unknown feedback 'median'"):
        generate(model, task, eps, feedback="median")
    with pytest.raises(ValueError, match="temperature"):
        generate(model, task, eps, feedback="segment_component", temperature=0.0)


def test_segment_track_keeps_the_drawn_mode_by_continuity():
    task = ToyReach(max_steps=10)
    model = _two_mode_model(task)
    eps = task.episodes(24, seed=0)
    committed = generate(model, task, eps, feedback="segment_component", seed=5)
    tracked = generate(model, task, eps, feedback="segment_track", seed=5)
    # the components' means never move, so the most responsible component is the one drawn at the start
    assert np.array_equal(tracked.components, committed.components)
    assert np.array_equal(tracked.q, committed.q)


@pytest.mark.parametrize("feedback", FEEDBACKS)
def test_k_models_in_one_call_roll_out_as_each_alone(overfit, feedback):
    """A list of K models runs one batched loop: each model's rollouts as alone up to float rounding (its own
    generator, every feedback mode, restarts included), and a list of one model exactly as the model alone."""
    task, demos, model = overfit
    torch.manual_seed(1)
    other = STM(model.config, task.layout, model.state_mean, model.state_std).eval()
    eps = [Episode(q0=ep.q0, psi=ep.psi, horizon=ep.horizon, info={"restart_steps": [5]})
           for ep in task.episodes(4, seed=2)]
    for m, ro in zip([model, other], generate([model, other], task, eps, feedback=feedback, seed=4), strict=True):
        alone = generate(m, task, eps, feedback=feedback, seed=4)
        np.testing.assert_allclose(ro.q, alone.q, atol=1e-5, rtol=0)
        assert np.array_equal(ro.components, alone.components) and np.array_equal(ro.grip, alone.grip)
    (one,) = generate([other], task, eps, feedback=feedback, seed=4)
    alone = generate(other, task, eps, feedback=feedback, seed=4)
    assert np.array_equal(one.q, alone.q) and np.array_equal(one.components, alone.components)
