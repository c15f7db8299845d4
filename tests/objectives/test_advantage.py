"""GroupRelativeAdvantage against hand-computed cases and a plain loop reference."""

from __future__ import annotations

import itertools
import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, ReplayBuffer

from torchrl_grpo.objectives import GroupRelativeAdvantage


def group_td(rewards: torch.Tensor, mask: torch.Tensor | None = None) -> TensorDict:
    """``rewards`` is [R, G, T]; returns the branch-group tensordict of the contract."""
    R, G, T = rewards.shape
    if mask is None:
        mask = torch.ones(R, G, T, dtype=torch.bool)
    return TensorDict(
        {
            "group_id": torch.arange(R).view(R, 1, 1).expand(R, G, T).clone(),
            "branch": torch.arange(G).view(1, G, 1).expand(R, G, T).clone(),
            "mask": mask,
            ("next", "reward"): rewards.unsqueeze(-1),
        },
        batch_size=[R, G, T],
    )


def adv_of(module: GroupRelativeAdvantage, td: TensorDict) -> torch.Tensor:
    return module(td)["advantage"].squeeze(-1)


# --------------------------------------------------------------- hand cases
def test_hand_mean_std_branch_returns():
    # returns 1, 2, 3: mean 2, unbiased std 1
    td = group_td(torch.tensor([[[1.0, 0.0], [1.0, 1.0], [2.0, 1.0]]]))
    adv = adv_of(GroupRelativeAdvantage(eps=0.0), td)
    expected = torch.tensor([-1.0, 0.0, 1.0]).view(3, 1).expand(3, 2)
    torch.testing.assert_close(adv[0], expected)
    assert adv.shape == (1, 3, 2)
    assert td["advantage"].shape == (1, 3, 2, 1)


def test_hand_eps_is_trl_formula():
    td = group_td(torch.tensor([[[1.0], [2.0], [3.0]]]))
    adv = adv_of(GroupRelativeAdvantage(eps=0.5), td)
    torch.testing.assert_close(adv[0, :, 0], torch.tensor([-1.0, 0.0, 1.0]) / 1.5)


def test_hand_leave_one_out_no_scale():
    # RLOO baselines: (2+3)/2, (1+3)/2, (1+2)/2
    td = group_td(torch.tensor([[[1.0], [2.0], [3.0]]]))
    adv = adv_of(GroupRelativeAdvantage(baseline="loo", scale_rewards="none"), td)
    torch.testing.assert_close(adv[0, :, 0], torch.tensor([-1.5, 0.0, 1.5]))


def test_hand_batch_std():
    # group means 1 and 12; batch std of [0, 2, 10, 14] (unbiased)
    td = group_td(torch.tensor([[[0.0], [2.0]], [[10.0], [14.0]]]))
    adv = adv_of(GroupRelativeAdvantage(scale_rewards="batch", eps=0.0), td)
    std = torch.tensor([0.0, 2.0, 10.0, 14.0]).std()
    torch.testing.assert_close(adv[..., 0], torch.tensor([[-1.0, 1.0], [-2.0, 2.0]]) / std)


def test_hand_dr_grpo_no_scale():
    td = group_td(torch.tensor([[[0.0], [2.0], [7.0]]]))
    adv = adv_of(GroupRelativeAdvantage(scale_rewards="none"), td)
    torch.testing.assert_close(adv[0, :, 0], torch.tensor([-3.0, -1.0, 4.0]))


def test_hand_discounted_branch_return():
    g = 0.5
    rewards = torch.tensor([[[1.0, 2.0, 4.0], [0.0, 0.0, 0.0]]])
    adv = adv_of(GroupRelativeAdvantage(gamma=g, scale_rewards="none"), group_td(rewards))
    ret = 1.0 + g * 2.0 + g**2 * 4.0  # 3.0 against 0.0: mean 1.5
    torch.testing.assert_close(adv[0, 0], torch.full((3,), ret / 2))
    torch.testing.assert_close(adv[0, 1], torch.full((3,), -ret / 2))


def test_hand_step_returns_grouped_by_depth():
    # branch 0 rewards 1, 1, 1 (rtg 3, 2, 1); branch 1 rewards 0, 2 then ended (rtg 2, 2)
    rewards = torch.tensor([[[1.0, 1.0, 1.0], [0.0, 2.0, 99.0]]])
    mask = torch.tensor([[[True, True, True], [True, True, False]]])
    adv = adv_of(
        GroupRelativeAdvantage(returns="step", scale_rewards="none"), group_td(rewards, mask)
    )
    expected = torch.tensor([[0.5, 0.0, 0.0], [-0.5, 0.0, 0.0]])
    # depth 0: rtg 3 vs 2; depth 1: 2 vs 2 (equal); depth 2: one member left -> 0
    torch.testing.assert_close(adv[0], expected)


def test_hand_step_returns_discounted():
    g = 0.9
    rewards = torch.tensor([[[1.0, 2.0], [0.0, 0.0]]])
    adv = adv_of(
        GroupRelativeAdvantage(returns="step", scale_rewards="none", gamma=g), group_td(rewards)
    )
    rtg0, rtg1 = 1.0 + g * 2.0, 2.0
    torch.testing.assert_close(adv[0, 0], torch.tensor([rtg0 / 2, rtg1 / 2]))


# ------------------------------------------------------------ edge behaviour
@pytest.mark.parametrize("baseline", ["mean", "loo"])
@pytest.mark.parametrize("scale", ["group", "batch", "none"])
@pytest.mark.parametrize("eps", [1e-4, 0.0])
def test_equal_returns_give_exact_zero(baseline, scale, eps):
    # three returns of 0.1 + 0.2: their float mean is not exactly their value, so a
    # rounding residue divided by eps (or 0 / 0 with eps = 0) would otherwise leak out
    rewards = torch.tensor([[[0.1, 0.2]] * 3, [[1.0, 0.0], [0.0, 3.0], [2.0, 2.0]]])
    module = GroupRelativeAdvantage(baseline=baseline, scale_rewards=scale, eps=eps)
    adv = adv_of(module, group_td(rewards))
    assert torch.equal(adv[0], torch.zeros(3, 2))
    assert torch.isfinite(adv).all()
    assert adv[1].abs().sum() > 0


def test_single_branch_group_is_an_error():
    rewards = torch.zeros(2, 3, 2)
    td = group_td(rewards)
    td["group_id"][1, 1:] = 7  # group 1 keeps one branch, group 7 gets two
    with pytest.raises(ValueError, match=r"groups \[1\].*single branch"):
        GroupRelativeAdvantage()(td)


def test_duplicate_group_branch_pairs_are_an_error_naming_first_group_id():
    # torch.cat of two branch_rollout outputs: both batches number their roots from 0
    a, b = group_td(torch.randn(2, 3, 4)), group_td(torch.randn(2, 3, 4))
    both = torch.cat([a, b])
    with pytest.raises(ValueError, match=r"\(group_id, branch\) pair \(0, 0\).*first_group_id"):
        GroupRelativeAdvantage()(both.clone())
    # the same data flattened to [N, T] or to [B] is refused the same way
    with pytest.raises(ValueError, match="first_group_id"):
        GroupRelativeAdvantage()(both.clone().reshape(12, 4))
    with pytest.raises(ValueError, match="first_group_id"):
        GroupRelativeAdvantage()(both.clone().reshape(-1))
    # two rows holding one pair next to each other are two trajectories too
    td = group_td(torch.randn(1, 2, 3)).reshape(2, 3)
    td = torch.cat([td[:1], td[:1], td[1:], td[1:]])
    with pytest.raises(ValueError, match=r"pair \(0, 0\)"):
        GroupRelativeAdvantage()(td)
    # distinct ids (what first_group_id gives the second batch) are accepted
    b["group_id"] += 2
    GroupRelativeAdvantage()(torch.cat([a, b]))


def test_trajectories_may_end_early_without_being_duplicates():
    # masked tails split no trajectory: the valid steps of each row stay one run
    mask = torch.ones(2, 3, 4, dtype=torch.bool)
    mask[0, 1, 2:] = False
    mask[1, 0, 1:] = False
    td = group_td(torch.randn(2, 3, 4), mask)
    for layout in (td.clone(), td.clone().reshape(6, 4), td.clone().reshape(-1)):
        GroupRelativeAdvantage()(layout)


@pytest.mark.parametrize("key", ["group_id", "branch", "mask", ("next", "reward")])
def test_missing_key_is_an_error(key):
    td = group_td(torch.randn(1, 2, 3))
    del td[key]
    with pytest.raises(ValueError, match=str(key[-1] if isinstance(key, tuple) else key)):
        GroupRelativeAdvantage()(td)


def test_nan_reward_on_valid_step_is_an_error_naming_the_group():
    rewards = torch.randn(3, 2, 4)
    rewards[2, 1, 0] = float("nan")
    with pytest.raises(ValueError, match=r"NaN.*\[2\]"):
        GroupRelativeAdvantage()(group_td(rewards))


def test_masked_steps_are_ignored_even_nan():
    rewards = torch.randn(2, 3, 4)
    mask = torch.ones(2, 3, 4, dtype=torch.bool)
    mask[:, :, 3] = False
    clean = adv_of(GroupRelativeAdvantage(), group_td(rewards[..., :3]))
    rewards[:, :, 3] = float("nan")
    adv = adv_of(GroupRelativeAdvantage(), group_td(rewards, mask))
    torch.testing.assert_close(adv[..., :3], clean)
    assert torch.equal(adv[..., 3], torch.zeros(2, 3))


def test_bad_options_and_shapes():
    with pytest.raises(ValueError, match="scale_rewards"):
        GroupRelativeAdvantage(scale_rewards="std")
    with pytest.raises(ValueError, match="gamma"):
        GroupRelativeAdvantage(gamma=0.0)
    td = group_td(torch.randn(1, 2, 3))
    td["mask"] = td["mask"].float()
    with pytest.raises(ValueError, match="boolean"):
        GroupRelativeAdvantage()(td)
    td = group_td(torch.randn(1, 2, 3))
    td["next", "reward"] = torch.randn(1, 2, 3, 2)
    with pytest.raises(ValueError, match="shape"):
        GroupRelativeAdvantage()(td)


def test_set_keys_renames_and_rejects_unknown():
    td = group_td(torch.tensor([[[1.0], [3.0]]]))
    td.rename_key_("group_id", "root")
    module = GroupRelativeAdvantage(eps=0.0).set_keys(group_id="root", advantage="adv")
    torch.testing.assert_close(
        module(td)["adv"].flatten(), torch.tensor([-1.0, 1.0]) / math.sqrt(2)
    )
    assert "root" in module.in_keys and module.out_keys == ["adv"]
    with pytest.raises(ValueError, match="not an accepted key"):
        module.set_keys(rewards="r")


# ------------------------------------------------------ layout independence
def test_layouts_agree():
    gen = torch.Generator().manual_seed(1)
    R, G, T = 3, 4, 5
    lengths = torch.randint(1, T + 1, (R, G, 1), generator=gen)
    td = group_td(torch.randn(R, G, T, generator=gen), torch.arange(T) < lengths)
    for returns in ("branch", "step"):
        module = GroupRelativeAdvantage(returns=returns, gamma=0.9)
        ref = adv_of(module, td.clone())
        flat_nt = adv_of(module, td.clone().reshape(R * G, T))
        flat_b = adv_of(module, td.clone().reshape(-1))
        torch.testing.assert_close(flat_nt.reshape(R, G, T), ref)
        torch.testing.assert_close(flat_b.reshape(R, G, T), ref)
        # whole trajectories in another order, flattened: ids, not positions, decide
        perm = torch.randperm(R * G, generator=gen)
        shuffled = td.clone().reshape(R * G, T)[perm].reshape(-1)
        adv = adv_of(module, shuffled).reshape(R * G, T)
        torch.testing.assert_close(adv, ref.reshape(R * G, T)[perm])


def test_replay_buffer_write_transform():
    td = group_td(torch.randn(2, 3, 4)).reshape(-1)
    expected = adv_of(GroupRelativeAdvantage(), td.clone())
    rb = ReplayBuffer(storage=LazyTensorStorage(100), batch_size=24)
    rb.append_transform(GroupRelativeAdvantage(), invert=True)
    rb.extend(td)
    torch.testing.assert_close(rb[:]["advantage"].squeeze(-1), expected)


# ------------------------------------------------------ loop reference
def loop_advantage(
    td: TensorDict, returns: str, baseline: str, scale: str, gamma: float, eps: float
):
    """Plain-Python reference: dictionaries of trajectories and groups, no vectorisation."""
    flat = td.reshape(-1)
    gid, br = flat["group_id"].tolist(), flat["branch"].tolist()
    rew, mask = flat["next", "reward"].squeeze(-1).tolist(), flat["mask"].tolist()
    trajs: dict[tuple[int, int], list[int]] = {}
    for i in range(len(gid)):
        if mask[i]:
            trajs.setdefault((gid[i], br[i]), []).append(i)
    units: dict[object, list[tuple[int, float]]] = {}  # group -> [(step or traj, value)]
    for (g, b), steps in trajs.items():
        if returns == "branch":
            value = sum(gamma**t * rew[i] for t, i in enumerate(steps))
            units.setdefault(g, []).append(((g, b), value))
        else:
            for t, i in enumerate(steps):
                value = sum(gamma**k * rew[j] for k, j in enumerate(steps[t:]))
                units.setdefault((g, t), []).append((i, value))
    all_values = [v for members in units.values() for _, v in members]
    batch_mean = sum(all_values) / len(all_values)
    batch_std = math.sqrt(sum((v - batch_mean) ** 2 for v in all_values) / (len(all_values) - 1))
    adv_of_unit = {}
    for members in units.values():
        values = [v for _, v in members]
        n = len(values)
        mean = sum(values) / n
        for unit, v in members:
            if n < 2 or max(values) == min(values):
                adv_of_unit[unit] = 0.0
                continue
            base = mean if baseline == "mean" else (sum(values) - v) / (n - 1)
            a = v - base
            if scale == "group":
                a /= math.sqrt(sum((x - mean) ** 2 for x in values) / (n - 1)) + eps
            elif scale == "batch":
                a /= batch_std + eps
            adv_of_unit[unit] = a
    out = [0.0] * len(gid)
    for (g, b), steps in trajs.items():
        for i in steps:
            out[i] = adv_of_unit[(g, b)] if returns == "branch" else adv_of_unit[i]
    return torch.tensor(out).reshape(td.batch_size)


@pytest.mark.parametrize(
    "returns,baseline,scale,gamma",
    [
        (r, b, s, g)
        for r, b, s, g in itertools.product(
            ["branch", "step"], ["mean", "loo"], ["group", "batch", "none"], [1.0, 0.95]
        )
    ],
)
def test_against_loop_reference(returns, baseline, scale, gamma):
    # a stable seed per case (str hashes change between processes)
    gen = torch.Generator().manual_seed(sum(map(ord, f"{returns}{baseline}{scale}{gamma}")))
    for _ in range(3):
        R, G, T = (int(x) for x in torch.randint(1, 6, (3,), generator=gen))
        G += 1  # groups of at least two branches
        rewards = torch.randn(R, G, T, generator=gen)
        # some groups with integer rewards, so that ties and all-equal groups occur
        rewards[: R // 2] = rewards[: R // 2].round().clamp(0, 1)
        lengths = torch.randint(1, T + 1, (R, G, 1), generator=gen)
        td = group_td(rewards, torch.arange(T) < lengths)
        module = GroupRelativeAdvantage(
            returns=returns, baseline=baseline, scale_rewards=scale, gamma=gamma, eps=1e-4
        )
        got = adv_of(module, td.clone())
        expected = loop_advantage(td, returns, baseline, scale, gamma, 1e-4)
        torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-5)
