"""A TorchRL env over any gymnasium env whose state a :class:`StateCodec` can capture.

The env follows TorchRL's deterministic-reset idiom: ``get_state()`` returns a
TensorDict of tensors, and ``reset(td_with_state, set_state=True)`` puts the
simulator back into exactly that state, in this process or in a worker of a
``ParallelEnv`` (the state travels through its shared buffers like any tensor).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from numbers import Integral
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Categorical, Composite, TensorSpec, Unbounded
from torchrl.envs import EnvBase
from torchrl.envs.libs.gym import _gym_to_torchrl_spec_transform

from torchrl_grpo.envs.core.action_validation import check_action, gym_action
from torchrl_grpo.envs.core.bits import (
    bits_spec,
    check_finite_floats,
    check_state_layout,
    flag_tensor,
    from_bits,
    nested_tensordict,
    spec_layout,
    to_bits,
)
from torchrl_grpo.envs.core.errors import SnapshotError, StateCorruptedError
from torchrl_grpo.envs.core.state_codec import StateCodec

logger = logging.getLogger(__name__)

STATE_KEY = "state"


class SnapshotEnv(EnvBase):
    """A gymnasium env, wrapped for TorchRL, whose complete state is a TensorDict.

    Args:
        env: a gymnasium env id, an env instance, or a callable that builds one.
        codec: the state codec for this simulator. Defaults to the codec registered
            for the env id (see :func:`~torchrl_grpo.envs.codec_for`).
        seed: seeds the first episode (``None``: gymnasium's entropy).
        return_state: also write the state *after* each step into the step's output
            (``("next", "state")``), so that any step of a collected trajectory can be
            branched from later. Costs one snapshot per step.
        categorical_action_encoding: discrete actions as integer indices (``True``)
            or one-hot vectors (``False``, TorchRL's ``GymEnv`` default).
        device: the device of the output tensors.
        make_kwargs: keyword arguments for ``gym.make`` when ``env`` is an id.
        check_actions: refuse an action outside the action spec before stepping, with an
            :class:`~torchrl_grpo.envs.InvalidActionError` (the env unchanged).

    The state has two parts: ``state["sim"]`` (the codec's encoding of the
    simulator) and ``state["output"]`` (the observation the env last returned,
    which a restore returns again without re-observing: observing may draw from
    the simulator's random generator).

    Example:
        >>> from torchrl.envs.utils import check_env_specs
        >>> env = SnapshotEnv("CartPole-v1", seed=0)
        >>> check_env_specs(env)
        >>> _ = env.reset()
        >>> state = env.get_state()
        >>> push = TensorDict(action=torch.tensor(1))
        >>> a = [env.step(push.clone())["next", "observation"] for _ in range(5)]
        >>> _ = env.reset(TensorDict(state=state), set_state=True)
        >>> b = [env.step(push.clone())["next", "observation"] for _ in range(5)]
        >>> all(torch.equal(x, y) for x, y in zip(a, b))
        True
    """

    _supports_set_state = True

    def __init__(
        self,
        env: str | gym.Env | Callable[[], gym.Env],
        codec: StateCodec | None = None,
        *,
        seed: int | None = None,
        return_state: bool = False,
        categorical_action_encoding: bool = True,
        device: torch.device | str = "cpu",
        make_kwargs: dict | None = None,
        check_actions: bool = True,
    ) -> None:
        super().__init__(device=device, batch_size=())
        if isinstance(env, str):
            env = gym.make(env, disable_env_checker=True, **(make_kwargs or {}))
        elif callable(env) and not isinstance(env, gym.Env):
            env = env()
        self._env: gym.Env = env
        if codec is None:
            from torchrl_grpo.envs.core.codec_registry import codec_for

            codec = codec_for(self._env_id())
        self.codec = codec
        self.return_state = return_state
        self.check_actions = check_actions
        self._categorical = categorical_action_encoding
        obs, info = self._gym_reset(seed)
        # The first reset() starts the seeded episode again (the one built here, which
        # the specs were read from), as "seed seeds the first episode" promises.
        self._pending_seed: int | None = seed
        codec.bind(self._env)
        self._make_specs(obs, info)
        # The last output as {key tuple: tensor}: a state stores it, a restore returns it.
        self._last_output = self._output_leaves(obs, info)

    # ------------------------------------------------------------------ specs
    def _env_id(self) -> str:
        spec = self._env.spec
        return spec.id if spec is not None else type(self._env.unwrapped).__name__

    def _make_specs(self, obs: Any, info: dict) -> None:
        self.action_spec = _gym_to_torchrl_spec_transform(
            self._env.action_space,
            device=self.device,
            categorical_action_encoding=self._categorical,
        )
        self._action_leaf = self.action_spec  # for the per-step check, read once
        self._name = f"{type(self).__name__}({self._env_id()!r})"
        obs_spec = _gym_to_torchrl_spec_transform(self._env.observation_space, device=self.device)
        if not isinstance(obs_spec, Composite):
            obs_spec = Composite(observation=obs_spec, device=self.device)
        for key, spec in self._info_spec(info).items():
            obs_spec[key] = spec
        self.observation_spec = obs_spec
        self._obs_dtypes = {key: obs_spec[key].dtype for key in obs_spec.keys()}
        self.reward_spec = Unbounded((1,), dtype=torch.float32, device=self.device)
        done = Categorical(2, (1,), dtype=torch.bool, device=self.device)
        self.done_spec = Composite(
            done=done.clone(), terminated=done.clone(), truncated=done.clone(), device=self.device
        )
        # The stored output holds floats as bit patterns, like the codecs' states.
        output_spec, self._output_floats = bits_spec(obs_spec)
        self._output_layout = spec_layout(output_spec)
        # Per stored output leaf: its key in the layout, its key tuple, its float dtype
        # (None: not stored as bits), computed once for the restore path.
        self._output_plan = [
            (key, key if isinstance(key, tuple) else (key,), self._output_floats.get(key))
            for key in self._output_layout
        ]
        state = Composite(sim=self.codec.state_spec(), output=output_spec, device=self.device)
        # In state_spec, so that reset(td, set_state=True) routes a state to every worker of
        # a batched env; with return_state also an observation, so that step_mdp carries
        # ("next", "state") to the root and batched envs and collectors return it.
        self.state_spec = Composite({STATE_KEY: state}, device=self.device)
        if self.return_state:
            self.observation_spec[STATE_KEY] = state.clone()

    #: Output entries whose NaN means "not reported", so a stored NaN is not refused.
    nan_outputs: frozenset[str] = frozenset()

    def _info_spec(self, info: dict) -> dict[Any, TensorSpec]:
        """Extra output entries; subclasses override it together with :meth:`_read_info`."""
        return {}

    def _read_info(self, info: dict) -> dict[Any, torch.Tensor]:
        """Tensors for the entries declared by :meth:`_info_spec`."""
        return {}

    # ------------------------------------------------------------------ state
    def get_state(self) -> TensorDict:
        """The complete current state: a new TensorDict of tensors only.

        Restore it with ``env.reset(TensorDict(state=state), set_state=True)``.
        """
        output = nested_tensordict({k: to_bits(v.clone()) for k, v in self._last_output.items()})
        state = TensorDict._new_unsafe(
            {"output": output, "sim": self.codec.encode(self._env)}, batch_size=torch.Size([])
        )
        return state if self.device.type == "cpu" else state.to(self.device)

    def set_state(self, state: TensorDictBase) -> TensorDict:
        """Restore a state from :meth:`get_state` and return the reset output.

        A shortcut for ``env.reset(TensorDict(state=state), set_state=True)``.
        """
        return self.reset(TensorDict({STATE_KEY: state}, batch_size=()), set_state=True)

    def reseed_state(self, state: TensorDictBase, seed: int | Sequence[int]) -> TensorDictBase:
        """Return a copy of ``state`` whose simulator random generator restarts from ``seed``.

        Only the generator changes (through the codec's
        :meth:`~torchrl_grpo.envs.StateCodec.reseed`, applied to ``state["sim"]``):
        restoring the result gives the same scene with the PCG64 stream of ``seed``,
        the one ``reset(seed=seed)`` would install. Use it to let branches restored
        from one state draw their own simulator randomness. ``state`` is untouched,
        and so is the env.

        States stacked to ``[N]`` take N seeds, so that a batched env reseeds a whole
        batch in one call to one worker (``penv[0].reseed_state(states, seeds)[0]``).

        Args:
            state: a state from :meth:`get_state` (of this env's config), or ``[N]``.
            seed: a non-negative int, or N of them for ``[N]`` states.

        Raises:
            StateMismatchError: the state belongs to another env or config.
            StateCorruptedError: a truncated state, or a batch of more than one dim.
            ValueError: a negative seed, or not one seed per state.
            NotImplementedError: this env's codec cannot reseed.

        Example:
            >>> from torchrl_grpo.envs import states_equal
            >>> env = SnapshotEnv("CartPole-v1", seed=0)
            >>> state = env.get_state()
            >>> a, b = env.reseed_state(state, 7), env.reseed_state(state, 7)
            >>> states_equal(a, b), states_equal(a, state)
            (True, False)
            >>> _ = env.set_state(a)  # CartPole draws from its generator on reset:
            >>> other = SnapshotEnv("CartPole-v1")
            >>> _ = other.set_seed(7)
            >>> torch.equal(env.reset()["observation"], other.reset()["observation"])
            True
            >>> env.reseed_state(torch.stack([state, state]), [1, 2]).batch_size
            torch.Size([2])
        """
        if not isinstance(state, TensorDictBase):
            raise StateCorruptedError(f"a state must be a TensorDict, got {type(state).__name__}")
        if state.batch_dims == 0:
            return self._reseed_one(state, seed)
        if state.batch_dims > 1:
            raise StateCorruptedError(
                f"reseed_state takes one state or states stacked to [N], got batch size "
                f"{tuple(state.batch_size)}"
            )
        seeds = [seed] if isinstance(seed, Integral) else list(seed)
        if len(seeds) != state.shape[0]:
            raise ValueError(f"{state.shape[0]} states need as many seeds, got {len(seeds)}")
        return torch.stack([self._reseed_one(state[i], s) for i, s in enumerate(seeds)])

    def _reseed_one(self, state: TensorDictBase, seed: int) -> TensorDictBase:
        self._check_envelope(state)
        out = state.exclude("sim").clone()
        out.set("sim", self.codec.reseed(state.get("sim"), seed))
        return out

    # ------------------------------------------------------------------ EnvBase
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDict:
        restoring = bool(kwargs.get("set_state"))
        if restoring:
            output = self._restore(tensordict)
            # The restored generator decides the next episodes: a seed still pending
            # (the constructor's, or set_seed before the restore) is dropped.
            self._pending_seed = None
        else:
            obs, info = self._gym_reset(self._pending_seed)
            self._pending_seed = None
            output = self._output_leaves(obs, info)
        self._last_output = output
        out = dict(output)
        for key in ("done", "terminated", "truncated"):
            out[(key,)] = torch.zeros((1,), dtype=torch.bool, device=self.device)
        if not restoring:
            # On restore the input tensordict already holds the state, and reset() returns
            # that tensordict updated: decode(encode(x)) is the identity on valid states.
            out[(STATE_KEY,)] = self.get_state()
        return nested_tensordict(out)

    def _restore(self, tensordict: TensorDictBase | None) -> dict[tuple[str, ...], torch.Tensor]:
        """Check and restore the state in ``tensordict``; return the output it stores."""
        if tensordict is None or STATE_KEY not in tensordict.keys():
            raise SnapshotError(
                f"reset(set_state=True) needs a tensordict holding a {STATE_KEY!r} entry "
                "(from env.get_state()); none was given"
            )
        state = tensordict.get(STATE_KEY)
        if not isinstance(state, TensorDictBase):
            raise StateCorruptedError(f"the {STATE_KEY!r} entry is not a TensorDict")
        if tuple(state.batch_size) != ():
            raise StateCorruptedError(
                f"this env is unbatched but the state has batch size {tuple(state.batch_size)}; "
                "restore batched states through a ParallelEnv / SerialEnv of matching size"
            )
        found = self._check_envelope(state)
        self.codec.decode(self._env, state.get("sim"))
        # Copies: the returned output must not share memory with the caller's state.
        output = {}
        for key, path, dtype in self._output_plan:
            value = found[key]
            output[path] = (value if dtype is None else from_bits(value, dtype)).clone()
        if self.device.type != "cpu":
            output = {k: v.to(self.device) for k, v in output.items()}
        return output

    def validate_state(self, state: TensorDictBase) -> None:
        """Run every check a restore runs, without modifying this env.

        ``state`` may be batched (each state is checked). Batched envs of snapshot
        envs should check states in the parent process before their workers restore
        them (a ``ParallelEnv`` worker that raises dies, and a ``SerialEnv`` restores
        the workers one after the other): :class:`~torchrl_grpo.envs.SnapshotParallelEnv`
        and :class:`~torchrl_grpo.envs.SnapshotSerialEnv` do.

        Raises:
            SnapshotError: the first state that does not fit, with the reason.

        Example:
            >>> from torchrl_grpo.envs import HighwayEnv, StateMismatchError
            >>> env = HighwayEnv("merge-v0", seed=0)
            >>> env.validate_state(env.get_state().expand(3))
            >>> try:
            ...     env.validate_state(HighwayEnv("highway-fast-v0", seed=0).get_state())
            ... except StateMismatchError as err:
            ...     print("refused")
            refused
        """
        if not isinstance(state, TensorDictBase):
            raise StateCorruptedError(f"a state must be a TensorDict, got {type(state).__name__}")
        for single in state.reshape(-1).unbind(0) if state.batch_dims else (state,):
            self._check_envelope(single)
            self.codec.validate(self._env, single.get("sim"))

    def _check_envelope(self, state: TensorDictBase) -> dict[Any, torch.Tensor]:
        """Check the parts of a state this class owns; return the output's leaves by key."""
        keys = state.keys()
        for part in ("sim", "output"):
            if part not in keys:
                raise StateCorruptedError(f"the state is truncated: it has no {part!r} part")
        # A state from another env must be reported as such, before any shape check.
        self.codec.check_compatible(state.get("sim"))
        found = check_state_layout(state.get("output"), self._output_layout)
        check_finite_floats(found, self._output_floats, "output", self.nan_outputs)
        return found

    def _step(self, tensordict: TensorDictBase) -> TensorDict:
        action = tensordict.get("action")
        if self.check_actions:  # before the simulator sees it: the env stays as it was
            check_action(action, self._action_leaf, self._name)
        obs, reward, terminated, truncated, info = self._env.step(
            gym_action(action, self._env.action_space, self._categorical)
        )
        self._last_output = self._output_leaves(obs, info)
        flat = dict(self._last_output)
        # Through numpy: torch.tensor() of a Python scalar costs twice as much.
        step = {
            ("reward",): torch.from_numpy(np.array([reward], dtype=np.float32)),
            ("terminated",): flag_tensor(terminated),
            ("truncated",): flag_tensor(truncated),
            ("done",): flag_tensor(terminated or truncated),
        }
        if self.device.type != "cpu":
            step = {k: v.to(self.device) for k, v in step.items()}
        flat.update(step)
        if self.return_state:
            flat[(STATE_KEY,)] = self.get_state()
        return nested_tensordict(flat)

    def _set_seed(self, seed: int | None) -> None:
        # Applied at the next fresh reset, as gymnasium seeds through reset(seed=...).
        self._pending_seed = seed

    # ------------------------------------------------------------------ gym glue
    def _gym_reset(self, seed: int | None) -> tuple[Any, dict]:
        if seed is not None:
            # Some envs sample their action space during reset (highway-env's reset info):
            # seed it too, so that a seed fixes the whole reset output.
            self._env.action_space.seed(seed)
        return self._env.reset(seed=seed)

    def _output_leaves(self, obs: Any, info: dict) -> dict[tuple[str, ...], torch.Tensor]:
        # Built leaf by leaf, without TensorDict validation: this runs on every step.
        if isinstance(obs, dict):
            entries = {("observation" if k == "state" else k): v for k, v in obs.items()}
        else:
            entries = {"observation": obs}
        dtypes = self._obs_dtypes
        out = {
            (key,): torch.as_tensor(np.array(value), dtype=dtypes[key], device=self.device)
            for key, value in entries.items()
        }
        for key, value in self._read_info(info).items():
            if isinstance(value, dict):
                out.update({(key, name): leaf for name, leaf in value.items()})
            else:
                out[(key,)] = value
        return out

    @property
    def gym_env(self) -> gym.Env:
        """The wrapped gymnasium env (read-only use: it is the simulator itself)."""
        return self._env

    def render(self) -> np.ndarray | None:
        """Render the current frame (needs ``render_mode="rgb_array"``)."""
        return self._env.render()

    def close(self, *, raise_if_closed: bool = True) -> None:
        """Close the gymnasium env and the TorchRL env."""
        self._env.close()
        super().close(raise_if_closed=raise_if_closed)
