"""Builders of the ``model`` group: the policy and the PPO value network."""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal, get_args

from omegaconf import DictConfig
from torch import nn
from torchrl.envs import EnvBase
from torchrl.modules import ProbabilisticActor, ValueOperator

from torchrl_grpo.modules.actors import make_discrete_actor, make_value_net
from torchrl_grpo.modules.crash_head import CrashHead
from torchrl_grpo.modules.ensemble import PolicyEnsemble
from torchrl_grpo.modules.networks import NetworkKind, make_network
from torchrl_grpo.modules.scene_features import DEFAULT_TARGET_SPEEDS, FeatureMLP, SceneMLP
from torchrl_grpo.modules.scripted.actions import (
    LONGITUDINAL_ACTIONS,
    META_ACTIONS,
    ConstantActionPolicy,
    ScriptedPolicy,
)
from torchrl_grpo.modules.scripted.policy_registry import make_scripted_policy
from torchrl_grpo.training.env_builder import make_layout

__all__ = [
    "BasePolicyName",
    "ModelArchitecture",
    "make_base_policy",
    "make_feature_mlp",
    "make_net",
    "make_policy",
    "make_value",
    "register_network_kind",
    "register_policy_wrapper",
    "set_crash_margin",
    "slower_action",
]

#: The core's networks of ``model.kind``: one of
#: :func:`~torchrl_grpo.modules.networks.make_network`'s kinds, or ``"scene"``
#: (:class:`~torchrl_grpo.modules.SceneMLP`). Others are registered
#: (:func:`register_network_kind`).
ModelArchitecture = Literal[NetworkKind, "scene"]
#: The scripted policies that drive deterministically (names of
#: :data:`~torchrl_grpo.modules.SCRIPTED_POLICIES`): a greedy tail's base (or a prior's).
BasePolicyName = Literal["idle", "slower", "rule", "conservative", "cautious"]

#: A wrapper of the policy's logits network: ``(model_cfg, env, net, n_actions) -> net``,
#: the network itself where its ``model`` keys are off.
PolicyWrapper = Callable[[DictConfig, EnvBase, nn.Module, int], nn.Module]
#: The wrappers :func:`make_policy` applies, in registration order
#: (:func:`register_policy_wrapper`): how a package beside the core, which the core never
#: imports (``torchrl_grpo.experimental``'s scripted prior), changes the policy every
#: builder of a run makes (training, evaluation, a teacher's reload).
POLICY_WRAPPERS: list[PolicyWrapper] = []

#: A builder of a registered network kind: ``(model_cfg, env, out_features) -> net``.
NetworkBuilder = Callable[[DictConfig, EnvBase, int], nn.Module]
#: The network kinds beside the core's (:data:`ModelArchitecture`), by name: their builder
#: and the ``model`` schema of the keys they read (:func:`register_network_kind`). How a
#: package the core never imports (``torchrl_grpo.experimental``'s ``neighbours``) adds a
#: network that :func:`make_net` builds for training, evaluation and a teacher's reload.
NETWORK_KINDS: dict[str, tuple[NetworkBuilder, type]] = {}


def register_network_kind(name: str, builder: NetworkBuilder, schema: type) -> NetworkBuilder:
    """Registers the network kind ``name``: :func:`make_net` builds it with ``builder``.

    ``builder(model_cfg, env, out_features)`` returns the network; ``schema`` is the
    ``model`` dataclass of the keys the kind reads (those an old config of that kind
    holds). Registering the same builder again is a no-op.

    Raises:
        ValueError: ``name`` is one of the core's kinds, or has another builder.

    Example:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_grpo.training.group_schemas import MLPModelConfig
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> def linear(model_cfg, env, out_features):
        ...     return nn.Sequential(nn.Flatten(-2), nn.LazyLinear(out_features))
        >>> _ = register_network_kind("linear", linear, MLPModelConfig)
        >>> cfg = OmegaConf.create({"kind": "linear"})
        >>> type(make_net(cfg, HighwayEnv(seed=0), 5)).__name__
        'Sequential'
        >>> del NETWORK_KINDS["linear"]  # leave the registry as it was
    """
    if name in get_args(ModelArchitecture) or name in get_args(NetworkKind):
        raise ValueError(f"model.kind={name} is one of the core's network kinds")
    known = NETWORK_KINDS.get(name)
    if known is not None and known[0] is not builder:
        raise ValueError(f"model.kind={name} is registered already, by {known[0].__qualname__}")
    NETWORK_KINDS[name] = (builder, schema)
    return builder


def register_policy_wrapper(wrapper: PolicyWrapper) -> PolicyWrapper:
    """Registers a wrapper of the policy's logits network (usable as a decorator).

    :func:`make_policy` hands it the ``model`` config, the env, the network (the
    ensemble, with ``model.ensemble > 1``) and the number of actions; it returns the
    network to act with. Registering the same function again is a no-op.

    Example:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_grpo.training.group_schemas import MLPModelConfig
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> class Doubled(nn.Module):
        ...     def __init__(self, net):
        ...         super().__init__()
        ...         self.net = net
        ...     def forward(self, observation):
        ...         return 2 * self.net(observation)
        >>> @register_policy_wrapper
        ... def doubled(model_cfg, env, net, n_actions):
        ...     return Doubled(net)
        >>> policy = make_policy(OmegaConf.structured(MLPModelConfig), HighwayEnv(seed=0))
        >>> type(policy.module[0].module).__name__
        'Doubled'
        >>> POLICY_WRAPPERS.remove(doubled)  # leave the registry as it was
    """
    if wrapper not in POLICY_WRAPPERS:
        POLICY_WRAPPERS.append(wrapper)
    return wrapper


def _table_shape(env: EnvBase) -> tuple[int, int]:
    shape = env.observation_spec["observation"].shape
    if len(shape) < 2:
        raise ValueError(
            f"the networks read a [vehicles, features] table; the env's observation has "
            f"shape {tuple(shape)} (use a Kinematics observation)"
        )
    return int(shape[-2]), int(shape[-1])


def make_net(model_cfg: DictConfig, env: EnvBase, out_features: int) -> nn.Module:
    """A network of kind ``model.kind`` from the env's observation table to ``out_features``.

    Example:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_grpo.training.group_schemas import MLPModelConfig
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> net = make_net(OmegaConf.structured(MLPModelConfig), HighwayEnv(seed=0), 5)
        >>> type(net).__name__
        'KinematicsMLP'
    """
    n_vehicles, n_features = _table_shape(env)
    kind = str(model_cfg.kind)
    registered = NETWORK_KINDS.get(kind)
    if registered is not None:
        return registered[0](model_cfg, env, out_features)
    if kind == "scene":
        return make_feature_mlp(SceneMLP, model_cfg, env, out_features)
    if kind == "mlp":
        kwargs = {"num_cells": list(model_cfg.num_cells)}
    elif kind == "transformer":
        layout = make_layout(env)
        if layout is None or "presence" not in layout.features:
            raise ValueError(
                "model.kind=transformer masks absent vehicles by the presence feature of "
                "highway-env's Kinematics observation; this env observes something else"
            )
        kwargs = {
            "presence_index": layout.index("presence"),
            **{key: int(model_cfg[key]) for key in ("embed_dim", "num_heads", "layers", "width")},
        }
    else:
        kwargs = {
            "embed_dim": int(model_cfg.embed_dim),
            "num_heads": int(model_cfg.num_heads),
            "encoder_cells": list(model_cfg.encoder_cells),
            "decoder_cells": list(model_cfg.decoder_cells),
        }
    return make_network(
        kind, n_vehicles=n_vehicles, n_features=n_features, out_features=out_features, **kwargs
    )


def make_feature_mlp(
    net_class: type[FeatureMLP], model_cfg: DictConfig, env: EnvBase, out_features: int
) -> nn.Module:
    """A :class:`~torchrl_grpo.modules.scene_features.FeatureMLP` of ``model.num_cells``.

    Its features are decoded from the env's Kinematics table, the speed centred on the
    env's own target speeds; errors name ``model.kind``.

    Example:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> cfg = OmegaConf.create({"kind": "scene", "num_cells": [8]})
        >>> type(make_feature_mlp(SceneMLP, cfg, HighwayEnv(seed=0), 5)).__name__
        'SceneMLP'
    """
    kind = str(model_cfg.kind)
    layout = make_layout(env)
    if layout is None:
        raise ValueError(
            f"model.kind={kind} reads highway-env's Kinematics observation; this env "
            "observes something else"
        )
    try:
        action = (getattr(env, "config", None) or {}).get("action", {})
        speeds = action.get("target_speeds") or DEFAULT_TARGET_SPEEDS
        return net_class(
            layout, out_features, num_cells=list(model_cfg.num_cells), target_speeds=speeds
        )
    except ValueError as err:
        raise ValueError(f"model.kind={kind}: {err}") from err


def make_policy(model_cfg: DictConfig, env: EnvBase) -> ProbabilisticActor:
    """The categorical policy: writes ``logits``, ``action`` and ``action_log_prob``.

    With ``model.crash_head``, the network has a second output per action, the logit of
    its crash probability (:class:`~torchrl_grpo.modules.CrashHead`), which
    ``model.crash_aversion`` weighs into the logits and by which ``model.crash_margin``
    bars the actions riskier than SLOWER. With ``model.ensemble=K > 1``, the
    policy is ``K`` such networks (:class:`~torchrl_grpo.modules.PolicyEnsemble`) that
    act with their mean logits. The wrappers of :data:`POLICY_WRAPPERS` then wrap the
    network (``torchrl_grpo.experimental``'s ``model.prior``).

    Example:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_grpo.training.group_schemas import MLPModelConfig
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> env = HighwayEnv(seed=0)
        >>> policy = make_policy(OmegaConf.structured(MLPModelConfig), env)
        >>> policy(env.reset())["action"].shape
        torch.Size([])
    """
    spec = env.action_spec
    if not hasattr(spec, "n"):
        raise ValueError(f"the policies here are discrete; the env's action spec is {spec}")
    n_actions = int(spec.n)
    size = int(model_cfg.get("ensemble", 1))
    if size < 1:
        raise ValueError(f"model.ensemble must be >= 1 (networks in the policy), got {size}")
    members = [_member(model_cfg, env, n_actions) for _ in range(size)]
    net = members[0] if size == 1 else PolicyEnsemble(members)
    for wrapper in POLICY_WRAPPERS:
        net = wrapper(model_cfg, env, net, n_actions)
    return make_discrete_actor(net, spec)


def _member(model_cfg: DictConfig, env: EnvBase, n_actions: int) -> nn.Module:
    """One logits network of the policy, with its crash head when ``model.crash_head``."""
    margin = model_cfg.get("crash_margin")
    if not model_cfg.get("crash_head", False):
        if margin is not None:
            raise ValueError(
                f"model.crash_margin={margin} bars actions by the crash head's "
                "probabilities; it needs model.crash_head=true"
            )
        return make_net(model_cfg, env, n_actions)
    net = make_net(model_cfg, env, 2 * n_actions)
    aversion = float(model_cfg.crash_aversion)
    if margin is None:
        return CrashHead(net, n_actions, aversion)
    return CrashHead(
        net, n_actions, aversion, margin=float(margin), fallback=slower_action(n_actions)
    )


def slower_action(n_actions: int) -> int:
    """SLOWER's index in highway-env's DiscreteMetaAction: 5 actions, or 3 longitudinal.

    The action a crash margin always allows (``model.crash_margin``).

    Example:
        >>> slower_action(5), slower_action(3)  # intersection-v0's SLOWER, IDLE, FASTER
        (4, 0)
    """
    if n_actions == len(LONGITUDINAL_ACTIONS):
        return LONGITUDINAL_ACTIONS["slower"]
    if n_actions == len(META_ACTIONS):
        return META_ACTIONS["SLOWER"]
    raise ValueError(
        f"model.crash_margin keeps SLOWER allowed, an action of highway-env's "
        f"DiscreteMetaAction (5 actions, or 3 longitudinal); this env has {n_actions}"
    )


def set_crash_margin(policy: nn.Module, margin: float | None) -> nn.Module:
    """Set ``model.crash_margin`` on a built policy's crash heads (None: no margin).

    The margin acts only on the greedy choice, so a trained run can be driven at another
    margin without training again: what ``benchmarks/bench_scenarios.py --crash-margin``
    does to a run's saved policy.

    Args:
        policy: a policy of :func:`make_policy` with ``model.crash_head=true`` (every
            member of an ensemble gets the margin).
        margin: how much likelier to crash than SLOWER an action may be and still be the
            greedy choice, in ``[0, 1]``; None: any action may be.

    Returns:
        ``policy``, changed in place.

    Raises:
        ValueError: the policy has no crash head, or the margin is not in ``[0, 1]``.

    Example:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_grpo.training.group_schemas import MLPModelConfig
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> cfg = OmegaConf.structured(MLPModelConfig(crash_head=True))
        >>> policy = set_crash_margin(make_policy(cfg, HighwayEnv(seed=0)), 0.01)
        >>> [m.margin for m in policy.modules() if isinstance(m, CrashHead)]
        [0.01]
    """
    heads = [m for m in policy.modules() if isinstance(m, CrashHead)]
    if not heads:
        raise ValueError(
            f"a crash margin of {margin} bars actions by the crash head's probabilities; "
            "this policy has none (train it with model.crash_head=true)"
        )
    for head in heads:
        fallback = None if margin is None else slower_action(head.n_actions)
        head.set_margin(margin, fallback)
    return policy


def make_base_policy(name: str, env: EnvBase, key: str) -> ScriptedPolicy:
    """The scripted policy ``name`` for ``env``; the error names the config ``key``.

    On a longitudinal-only action set (intersection-v0's SLOWER, IDLE, FASTER) the
    constant policies ``slower``, ``idle`` and ``faster`` apply, and no other.

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> type(make_base_policy("rule", HighwayEnv(seed=0), "algo.tail_policy")).__name__
        'RulePolicy'
    """
    n_actions = getattr(env.action_spec, "n", None)
    if n_actions == len(LONGITUDINAL_ACTIONS) and name in LONGITUDINAL_ACTIONS:
        return ConstantActionPolicy(LONGITUDINAL_ACTIONS[name])
    layout = make_layout(env)
    if n_actions != 5 or layout is None:
        raise ValueError(
            f"{key}={name} is a scripted policy of highway-env's 5-action "
            "DiscreteMetaAction on Kinematics observations; this env has "
            f"{n_actions or 'continuous'} actions"
            + ("" if layout is not None else " and no Kinematics observation")
            + (
                f" (on its 3 longitudinal actions: {', '.join(LONGITUDINAL_ACTIONS)})"
                if n_actions == len(LONGITUDINAL_ACTIONS)
                else ""
            )
        )
    try:
        return make_scripted_policy(name, layout)
    except ValueError as err:
        raise ValueError(f"{key}={name}: {err}") from err


def make_value(model_cfg: DictConfig, env: EnvBase) -> ValueOperator:
    """The PPO critic (same architecture as the policy, one output).

    Example:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_grpo.training.group_schemas import MLPModelConfig
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> env = HighwayEnv(seed=0)
        >>> make_value(OmegaConf.structured(MLPModelConfig), env)(env.reset())["state_value"].shape
        torch.Size([1])
    """
    return make_value_net(make_net(model_cfg, env, 1))
