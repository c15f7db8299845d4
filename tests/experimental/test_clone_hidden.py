"""clone_hidden's hidden rows against a hand-built world, and clone_heads' stage guard."""

import sys

import clone_heads
import clone_hidden
import pytest
import torch

from torchrl_grpo.envs import tensor_params
from torchrl_grpo.sim.state import empty_world, world_to_tensordict

pytestmark = pytest.mark.experimental


def test_each_row_holds_the_hidden_state_of_the_vehicle_the_observation_shows():
    # The ego at x = 100 m in lane 1, changing to lane 2; vehicle 1 is 400 m ahead (out of
    # sight), vehicle 2 is 30 m ahead and vehicle 3 10 m behind: the table shows the ego,
    # then vehicle 3 (the nearer), then vehicle 2, then nothing.
    world = empty_world(1, 4, torch.float64)
    v = world.vehicles._replace(
        x=torch.tensor([[100.0, 500.0, 130.0, 90.0]], dtype=torch.float64),
        target_speed=torch.tensor([[30.0, 21.0, 22.0, 23.0]], dtype=torch.float64),
        timer=torch.tensor([[0.0, 0.1, 0.2, 0.3]], dtype=torch.float64),
        lane=torch.tensor([[1, 0, 0, 2]]),
        target_lane=torch.tensor([[2, 0, 1, 2]]),
    )
    state = world_to_tensordict(world._replace(vehicles=v))
    observation = {"type": "Kinematics", "see_behind": True}  # as the clone's run
    params = tensor_params("highway-fast-v0", {"observation": observation})
    rows = clone_hidden.hidden_rows(state, params)
    expected = [
        [30.0, 0.0, 1.0],  # the ego: its set-point, its timer, one lane to the left
        [23.0, 0.3, 0.0],  # vehicle 3
        [22.0, 0.2, 1.0],  # vehicle 2, changing lanes
        [0.0, 0.0, 0.0],
        [0.0, 0.0, 0.0],
    ]
    assert rows.shape == (1, 5, 3)
    assert torch.allclose(rows[0], torch.tensor(expected))


def test_stages_that_act_at_one_aversion_refuse_several(monkeypatch, capsys):
    argv = ["clone_heads.py", "fit", "--tail", "x.pt", "--act-aversion", "30", "100"]
    monkeypatch.setattr(sys, "argv", argv)
    with pytest.raises(SystemExit):
        clone_heads.main()
    assert "fit acts at one --act-aversion, not [30.0, 100.0]" in capsys.readouterr().err
