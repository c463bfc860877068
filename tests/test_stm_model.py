import pytest
import torch
from stm_toytask import ToyReach, single_torch_thread  # noqa: F401  (autouse)

from envs.kinematics import default_kinematics
from stm.config import ModelConfig, TrainConfig
from stm.model import STM, feedback_state, initial_state, normalization_stats

KIN = default_kinematics(torch.float32)


def test_configs_round_trip_and_reject_unknown_keys():
    m, t = ModelConfig(hidden_size=8, mixtures=5), TrainConfig(u=2, v=3, feedback="sample")
    assert ModelConfig.from_dict(m.to_dict()) == m and TrainConfig.from_dict(t.to_dict()) == t
    with pytest.raises(ValueError, match="unknown ModelConfig key 'hiden_size'"):
        ModelConfig.from_dict({"hiden_size": 3})
    with pytest.raises(ValueError, match=r"TrainConfig\s+feedback"):
        TrainConfig(feedback="median")
    with pytest.raises(ValueError, match=r"ModelConfig\s+head"):
        ModelConfig(head="gmm")


@pytest.mark.parametrize("gripper", [False, True])
def test_grounded_feedback_recomputes_phi_by_fk_and_takes_psi_from_task(gripper):
    task = ToyReach(gripper=gripper)
    L = task.layout
    g = torch.Generator().manual_seed(0)
    q_prev = torch.as_tensor(task.demos(0).q[:4, 3], dtype=torch.float32)
    pred = torch.randn(4, L.dim, generator=g)
    pred[:, L.dq] *= 0.05
    psi = torch.randn(4, L.psi_dim, generator=g)
    s, q = feedback_state(task, KIN, pred, q_prev, psi, "grounded")
    torch.testing.assert_close(q, q_prev + pred[:, L.dq])
    torch.testing.assert_close(s[:, L.dq], pred[:, L.dq], atol=1e-6, rtol=0)
    torch.testing.assert_close(s[:, L.phi], KIN.tip_position(q) - psi)  # FK of the integrated q, not pred
    assert not torch.allclose(s[:, L.phi], pred[:, L.phi])
    torch.testing.assert_close(s[:, L.psi], psi)
    if gripper:
        assert set(s[:, L.grip].flatten().tolist()) <= {0.0, 1.0}
    free, _ = feedback_state(task, KIN, pred, q_prev, psi, "free")
    torch.testing.assert_close(free[:, L.phi], pred[:, L.phi])
    torch.testing.assert_close(free[:, L.psi], psi)


def test_feedback_gradient_flows_through_fk():
    task = ToyReach()
    pred = torch.zeros(2, task.layout.dim, requires_grad=True)
    q_prev = torch.as_tensor(task.demos(0).q[:2, 0], dtype=torch.float32)
    s, _ = feedback_state(task, KIN, pred, q_prev, torch.zeros(2, 3), "grounded")
    s[:, task.layout.phi].sum().backward()
    assert pred.grad[:, task.layout.dq].abs().sum() > 0  # d phi / d dq through the kinematics


def test_initial_state_matches_demo_states():
    task = ToyReach(gripper=True)
    demos = task.demos(0)
    states = torch.as_tensor(task.demo_states(demos, KIN))
    q0 = torch.as_tensor(demos.q[:, 0], dtype=torch.float32)
    s0 = initial_state(task, KIN, q0, torch.as_tensor(demos.psi[:, 0], dtype=torch.float32))
    torch.testing.assert_close(s0, states[:, 0].float(), atol=1e-5, rtol=0)


def test_a_constant_state_dimension_gets_its_parts_std_floor():
    """The circle's tip height is constant in its demos: its std must not be ~0 (a 1 mm drift
    would read as ~1000 std in closed loop)."""
    from stm.model import STD_FLOORS

    task = ToyReach(gripper=True)
    layout = task.layout
    states = torch.randn(4, 9, layout.dim) * 0.2
    states[..., layout.phi.start + 2] = 0.0  # constant phi_z
    mask = torch.ones(4, 9, dtype=torch.bool)
    mean, std = normalization_stats(states, mask, layout)
    assert std[layout.phi.start + 2] == STD_FLOORS["phi"]
    plain_mean, plain_std = normalization_stats(states, mask)
    assert plain_std[layout.phi.start + 2] < 1e-5  # without a layout: the old tiny floor
    others = torch.ones(layout.dim, dtype=torch.bool)
    others[layout.phi.start + 2] = False
    torch.testing.assert_close(std[others], plain_std[others])  # spreads above the floors are untouched
    torch.testing.assert_close(mean, plain_mean)


def test_loss_ignores_padded_steps_and_normalisation_round_trips():
    task = ToyReach()
    D = task.layout.dim
    states = torch.randn(3, 6, D)
    mask = torch.ones(3, 6, dtype=torch.bool)
    mask[0, 4:] = False
    mean, std = normalization_stats(states, mask)
    for head in ("mdn", "deterministic"):
        model = STM(ModelConfig(hidden_size=8, num_layers=2, head=head), task.layout, mean, std)
        torch.testing.assert_close(model.denormalize(model.normalize(states)), states, atol=1e-5, rtol=0)
        raw, _ = model(model.normalize(states[:, :-1]))
        target = model.normalize(states[:, 1:])
        loss = model.loss(raw, target, mask[:, 1:])
        target2 = target.clone()
        target2[0, 4:] = 1e6  # padded rows
        assert torch.equal(loss, model.loss(raw, target2, mask[:, 1:]))
        target2[0, 0] += 1.0
        assert not torch.equal(loss, model.loss(raw, target2, mask[:, 1:]))
