import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded, Categorical, OneHot
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor, ValueOperator

from torchrl_grpo.modules import EgoAttentionNet, KinematicsMLP, make_discrete_actor, make_value_net
from torchrl_grpo.modules.actors import DeterministicActor, make_continuous_actor

V, F, N_ACTIONS = 5, 5, 5


def _td(*batch: int) -> TensorDict:
    torch.manual_seed(1)
    obs = torch.randn(*batch, V, F)
    obs[..., 0] = 1.0
    return TensorDict(observation=obs, batch_size=batch)


@pytest.fixture(params=["mlp", "ego_attention"])
def logits_net(request):
    torch.manual_seed(0)
    if request.param == "mlp":
        return KinematicsMLP(V, F, N_ACTIONS, num_cells=(16,))
    return EgoAttentionNet(F, N_ACTIONS, embed_dim=8, num_heads=2)


def test_discrete_actor_samples_valid_actions_with_matching_log_probs(logits_net):
    actor = make_discrete_actor(logits_net, Categorical(N_ACTIONS))
    assert isinstance(actor, ProbabilisticActor)
    td = actor(_td(2, 3, 4))
    action = td["action"]
    assert action.shape == (2, 3, 4) and action.dtype == torch.int64
    assert ((action >= 0) & (action < N_ACTIONS)).all()
    expected = torch.log_softmax(td["logits"], -1).gather(-1, action.unsqueeze(-1)).squeeze(-1)
    torch.testing.assert_close(td[actor.log_prob_keys[0]], expected)
    dist = actor.get_dist(td)
    torch.testing.assert_close(dist.log_prob(action), expected)


def test_discrete_actor_samples_by_default_and_follows_the_distribution():
    # A network that ignores its input: logits fixed to a known distribution.
    probs = torch.tensor([0.1, 0.2, 0.3, 0.4, 0.0])

    class Fixed(torch.nn.Module):
        def forward(self, obs):
            return probs.log().expand(*obs.shape[:-2], N_ACTIONS)

    actor = make_discrete_actor(Fixed(), N_ACTIONS)
    actions = actor(_td(4000))["action"]
    freq = torch.bincount(actions, minlength=N_ACTIONS).float() / actions.numel()
    torch.testing.assert_close(freq, probs, atol=0.03, rtol=0)
    assert actions.unique().numel() > 1


def test_deterministic_mode_is_argmax(logits_net):
    actor = make_discrete_actor(logits_net, N_ACTIONS)
    td = _td(64)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        greedy = actor(td.clone())
    assert (greedy["action"] == greedy["logits"].argmax(-1)).all()
    wrapped = DeterministicActor(actor)
    # The wrapper wins over an outer RANDOM context, as set by collectors.
    with set_exploration_type(ExplorationType.RANDOM):
        out = wrapped(td.clone())
    assert (out["action"] == greedy["action"]).all()
    assert wrapped.in_keys == actor.in_keys
    with pytest.raises(ValueError):
        DeterministicActor(actor, ExplorationType.RANDOM)


def test_one_hot_spec_gives_one_hot_actions(logits_net):
    actor = make_discrete_actor(logits_net, OneHot(N_ACTIONS))
    td = actor(_td(7))
    assert td["action"].shape == (7, N_ACTIONS)
    assert (td["action"].sum(-1) == 1).all()


def test_discrete_actor_rejects_continuous_spec(logits_net):
    with pytest.raises(TypeError):
        make_discrete_actor(logits_net, Bounded(-1, 1, shape=(2,)))


@pytest.mark.parametrize("distribution", ["tanh_normal", "normal"])
def test_continuous_actor(distribution):
    torch.manual_seed(0)
    spec = Bounded(torch.tensor([-1.0, -0.5]), torch.tensor([1.0, 0.5]), shape=(2,))
    net = EgoAttentionNet(F, out_features=4, embed_dim=8, num_heads=2)
    actor = make_continuous_actor(net, spec, distribution=distribution)
    td = actor(_td(3, 4))
    action = td["action"]
    assert action.shape == (3, 4, 2)
    assert (td["scale"] > 0).all()
    log_prob = td[actor.log_prob_keys[0]]
    assert log_prob.shape == (3, 4) and torch.isfinite(log_prob).all()
    dist = actor.get_dist(td)
    torch.testing.assert_close(dist.log_prob(action), log_prob, rtol=1e-4, atol=1e-4)
    if distribution == "tanh_normal":
        assert (action.abs() <= spec.space.high).all()
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        det1 = actor(td.clone())["action"]
        det2 = actor(td.clone())["action"]
    torch.testing.assert_close(det1, det2)
    if distribution == "normal":
        torch.testing.assert_close(det1, td["loc"])


def test_continuous_actor_from_dimension():
    actor = make_continuous_actor(KinematicsMLP(V, F, 4, num_cells=(8,)), 2)
    assert actor(_td(5))["action"].shape == (5, 2)


def test_value_net(logits_net):
    torch.manual_seed(0)
    critic = make_value_net(EgoAttentionNet(F, out_features=1, embed_dim=8, num_heads=2))
    assert isinstance(critic, ValueOperator)
    assert critic(_td(2, 3))["state_value"].shape == (2, 3, 1)


def test_actor_in_env_rollout():
    import highway_env  # noqa: F401  (registers the scenarios)
    from torchrl.envs import GymEnv

    env = GymEnv("highway-fast-v0", categorical_action_encoding=True)
    actor = make_discrete_actor(
        EgoAttentionNet(F, N_ACTIONS, embed_dim=8, num_heads=2), env.action_spec
    )
    env.set_seed(0)
    td = env.rollout(3, policy=actor, break_when_any_done=True)
    assert td["action"].dtype == torch.int64
    assert "action_log_prob" in td.keys()
    env.close()


def test_continuous_actor_in_env_rollout():
    import highway_env  # noqa: F401
    from torchrl.envs import GymEnv

    env = GymEnv("highway-fast-v0", config={"action": {"type": "ContinuousAction"}})
    dim = env.action_spec.shape[-1]
    actor = make_continuous_actor(KinematicsMLP(V, F, 2 * dim, num_cells=(16,)), env.action_spec)
    td = env.rollout(2, policy=actor, auto_reset=False, tensordict=env.reset(seed=0))
    assert td["action"].shape == (td.shape[0], dim)
    assert env.action_spec.is_in(td["action"][0])
    env.close()
