"""TensorHighwayEnv: B highway-env worlds in one batched tensor simulator.

The env wraps :mod:`torchrl_grpo.sim` in TorchRL's ``EnvBase``, with the specs and
output keys of :class:`~torchrl_grpo.envs.HighwayEnv` for the same scenario, so that
policies, the GRPO loss and the trainer run on either unchanged. Its state is a
TensorDict ``[B]`` of tensors (:meth:`TensorHighwayEnv.get_state`, laid out in
:mod:`.tensor_state`): a snapshot is a clone, branches are copies along the batch
dimension, and ``reset(TensorDict(state=...), set_state=True)`` restores any rows.
"""

from __future__ import annotations

from collections.abc import Sequence
from numbers import Integral
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Categorical, Composite, OneHot, Unbounded
from torchrl.envs import EnvBase

from torchrl_grpo.envs.core.action_validation import check_action
from torchrl_grpo.envs.core.errors import SnapshotError
from torchrl_grpo.envs.core.gym_state import RNG_WORDS
from torchrl_grpo.envs.core.snapshot_env import STATE_KEY
from torchrl_grpo.envs.core.state_codec import stable_hash
from torchrl_grpo.envs.highway.bridge import HighwayBridge, export_states, import_states
from torchrl_grpo.envs.highway.step_modes import compiled_mode, eager_mode, native_mode
from torchrl_grpo.envs.highway.tensor_models import (
    output_tensordict,
    tensor_model,
    zero_fresh_rewards,
)
from torchrl_grpo.envs.highway.tensor_params import check_tensor_config, tensor_params
from torchrl_grpo.envs.highway.tensor_state import (
    check_state_structure,
    check_state_values,
    reseeded,
    tensor_state_spec,
    where_rows,
)
from torchrl_grpo.sim.rng import seed_keys
from torchrl_grpo.sim.state import (
    empty_world,
    world_from_tensordict,
    world_to_tensordict,
)

__all__ = ["TensorHighwayEnv"]


class TensorHighwayEnv(EnvBase):
    """A scenario of ``TENSOR_SCENARIOS`` as ``num_envs`` worlds at once.

    Args:
        scenario: highway-v0, highway-fast-v0, merge-v0, roundabout-v0 or intersection-v0
            (the last three: row ``i`` starts as ``HighwayEnv(scenario)`` after ``reset(seed=
            seed + i)``, eagerly; intersection-v0's later spawns draw from the row's stream).
        config: overrides of the scenario's config, within what
            :func:`~torchrl_grpo.envs.check_tensor_config` covers (anything else is a
            ``ValueError`` naming it).
        num_envs: B, the worlds stepped together.
        device: where the worlds live (``"cuda"`` without a GPU is a ``ValueError``).
        dtype: float dtype of the simulation and of every float spec
            (``torch.float64`` for step-by-step parity with highway-env).
        seed: seeds the worlds' random streams (``None``: drawn from torch's generator).
        return_state: write each step's state into the trajectory.
        compile: TorchRL's keyword of every env: ``True``, or a dict of
            ``torch.compile`` options, calls :meth:`compile` (the step, static shapes).
        check_states: check the values of restored states (finite floats, lanes and
            indices in range, valid generator words); structure and config are checked
            always. Turn off for speed once states are known good.
        check_actions: refuse, before stepping, actions outside the action spec with an
            :class:`~torchrl_grpo.envs.InvalidActionError` naming rows and values (the env
            is left unchanged). One comparison a step, read back (a sync on a GPU).
        categorical_action_encoding: integer actions (``False``: one-hot).
        native: step in C++ on the CPU (:meth:`native`: every scenario of the tensor
            simulator), the fastest step there (docs/sim.md, "Speed").

    Example:
        >>> from torchrl.envs.utils import check_env_specs
        >>> env = TensorHighwayEnv("highway-fast-v0", num_envs=8, seed=0)
        >>> check_env_specs(env)
        >>> td = env.reset()
        >>> state = env.get_state()  # every world, complete
        >>> roots = state[:2].repeat_interleave(4, 0)  # 2 roots x 4 branches
        >>> td = env.reset(TensorDict(state=roots, batch_size=[8]), set_state=True)
        >>> td = env.rollout(5, break_when_any_done=False, auto_reset=False, tensordict=td)
        >>> td["next", "observation"].shape
        torch.Size([8, 5, 5, 5])
    """

    _supports_set_state = True
    batch_locked = True
    #: Rows are independent worlds restored and stepped together: branch rollouts run
    #: all their branches as rows of one batched rollout (see torchrl_grpo.branching).
    batched_worlds = True

    def __init__(
        self,
        scenario: str = "highway-fast-v0",
        config: dict | None = None,
        *,
        num_envs: int = 1,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float32,
        seed: int | None = None,
        return_state: bool = False,
        check_states: bool = True,
        check_actions: bool = True,
        categorical_action_encoding: bool = True,
        native: bool = False,
    ) -> None:
        if dtype not in (torch.float32, torch.float64):
            raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
        if not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive int, got {num_envs!r}")
        device = torch.device(device)
        if device.type == "cuda" and not torch.cuda.is_available():
            raise ValueError("device='cuda' was asked for, but torch finds no CUDA device")
        self.params = tensor_params(scenario, config)
        self._regulated = hasattr(self.params, "regulation")  # intersection-v0's state fields
        self._model = tensor_model(scenario)
        super().__init__(device=device, batch_size=torch.Size([num_envs]))
        self.scenario = scenario
        self.overrides = dict(config or {})
        self.config = check_tensor_config(scenario, config)
        self.dtype = dtype
        self.return_state = return_state
        self.check_states = check_states
        self.check_actions = check_actions
        self._categorical = categorical_action_encoding
        self._bridge: HighwayBridge | None = None
        self.fingerprint = stable_hash("TensorHighwayEnv", scenario, repr(self.params), str(dtype))
        (self.native if native else self.eager)()  # the step mode
        self._world = empty_world(
            num_envs, self.params.num_vehicles, dtype, device, self._route_length, self._regulated
        )
        #: Worlds stepped so far, masked rows included (the simulator's throughput).
        self.world_steps = 0
        self._highway_rng = torch.zeros(num_envs, RNG_WORDS, dtype=torch.int64, device=device)
        self._highway_seed = torch.full((num_envs,), -1, dtype=torch.int64, device=device)
        self._set_seed(int(torch.empty((), dtype=torch.int64).random_()) if seed is None else seed)
        self._make_specs()
        # Valid worlds from the start (get_state before a reset restores), and the first
        # reset draws the same ones again: the seed seeds the first episodes.
        counter, words = self._world.rng_counter, self._highway_rng
        self._reset()
        self._world = self._world._replace(rng_counter=counter)
        if self._model.draws_from_words:
            self._highway_rng = words

    def compile(
        self, *, warmup: int | None = None, dense: bool | None = None, **kwargs: Any
    ) -> TensorHighwayEnv:
        """Run the step through ``torch.compile`` (static shapes); ``self``.

        What ``TensorHighwayEnv(..., compile=True)`` (or ``compile={...}``, TorchRL's
        constructor keyword) calls; see :func:`.step_modes.compiled_mode`.

        Args:
            warmup: accepted for TorchRL's signature (the first call compiles).
            dense: compile the dense step, one substep and the observation (default:
                on a GPU only).
            **kwargs: forwarded to ``torch.compile`` (``dynamic`` defaults to ``False``).

        Example:
            >>> env = TensorHighwayEnv(num_envs=4, compile=True)  # compiles at its first step
            >>> env.eager() is env  # eager steps again
            True
        """
        self._mode = compiled_mode(self._model, self.params, self.device, dense, **kwargs)
        return self

    def native(self, threads: int | None = None) -> TensorHighwayEnv:
        """Step in C++ on the CPU (every scenario of the tensor simulator); ``self``.

        A loop per world over ``threads`` (default ``torch.get_num_threads()``), the fastest
        step on a CPU: see :mod:`torchrl_grpo.sim.native`, :mod:`~torchrl_grpo.sim.routed_native`,
        :mod:`~torchrl_grpo.sim.intersection_native`.

        Raises:
            ValueError: a GPU, or a config the C++ step cannot hold (the env stays as it was).
            NativeBuildError: no C++ compiler to build it.

        Example:
            >>> env = TensorHighwayEnv(num_envs=4).native()
            >>> env.eager() is env  # the tensor step again
            True
        """
        self._mode = native_mode(self.scenario, self.params, self.device, threads)
        return self

    @property
    def step_mode(self) -> str:
        """How the worlds step: ``"eager"``, ``"compiled"`` or ``"native"`` (C++)."""
        return self._mode.name

    def eager(self) -> TensorHighwayEnv:
        """Step with the tensor path again (after :meth:`compile` or :meth:`native`); ``self``."""
        self._mode = eager_mode(self._model, self.params, self.device)
        return self

    def _make_specs(self) -> None:
        b, d, dev = self.batch_size, self.dtype, self.device
        obs = self.params.observation
        flag = Categorical(2, (*b, 1), dtype=torch.bool, device=dev)

        def real(*shape: int) -> Unbounded:
            return Unbounded((*b, *shape), dtype=d, device=dev)

        parts = Composite({n: real(1) for n in self._model.components}, shape=b, device=dev)
        spec = Composite(
            observation=real(obs.vehicles_count, len(obs.features)),
            crashed=flag.clone(),
            on_road=flag.clone(),
            speed=real(1),
            ego_position=real(2),
            ego_heading=real(1),
            reward_components=parts,
            shape=b,
            device=dev,
        )
        n = self._model.actions
        if self._categorical:
            self.action_spec = Categorical(n, b, dtype=torch.int64, device=dev)
        else:
            self.action_spec = OneHot(n, (*b, n), dtype=torch.int64, device=dev)
        # Kept for the per-step check: reading action_spec goes through the input spec.
        self._action_leaf = self.action_spec
        self._name = f"TensorHighwayEnv({self.scenario!r}, num_envs={b[0]})"
        self.reward_spec = real(1)
        self.done_spec = Composite(
            done=flag.clone(), terminated=flag.clone(), truncated=flag.clone(), shape=b, device=dev
        )
        n = self.params.num_vehicles
        state = tensor_state_spec(b, n, d, dev, self._route_length, self._regulated)
        self.state_spec = Composite({STATE_KEY: state}, shape=b, device=dev)
        if self.return_state:
            spec[STATE_KEY] = state.clone()
        self.observation_spec = spec

    @property
    def _route_length(self) -> int:
        """The legs a vehicle's route holds (routed scenarios), 0 where there are no routes."""
        return getattr(self.params, "route_length", 0)

    # ------------------------------------------------------------------ state
    def get_state(self) -> TensorDict:
        """Every world's complete state: a new TensorDict ``[B]`` of tensors.

        Restore rows with ``env.reset(TensorDict(state=state, batch_size=[B]), set_state=True)``.
        """
        state = world_to_tensordict(self._world)
        batch = self.batch_size
        state.set(
            "highway", TensorDict(rng=self._highway_rng, seed=self._highway_seed, batch_size=batch)
        )
        state.set(
            "fingerprint",
            torch.full(batch, self.fingerprint, dtype=torch.int64, device=self.device),
        )
        return state.clone()

    def validate_state(self, state: TensorDictBase) -> None:
        """Run every check a restore runs on ``state`` (any batch ``[M]``), changing nothing.

        Raises:
            StateCorruptedError: a truncated state, wrong shapes, dtypes or devices, and
                (with ``check_states``) non-finite values, lanes or indices out of range,
                invalid generator words.
            StateMismatchError: a state of another scenario, config or dtype.
        """
        check_state_structure(state, self.state_spec[STATE_KEY], self.fingerprint)
        if self.check_states:
            check_state_values(state, self.params)

    def reseed_state(self, state: TensorDictBase, seed: int | Sequence[int]) -> TensorDict:
        """A copy of ``state`` (``[M]``) whose random streams restart from ``seed`` (one per row).

        The world itself is kept; its next fresh episode, and the generator highway-env
        gets through the bridge, come from the seed.
        """
        self.validate_state(state)
        n = state.shape[0]
        seeds = [int(seed)] * n if isinstance(seed, Integral) else [int(s) for s in seed]
        if len(seeds) != n or min(seeds, default=0) < 0:
            raise ValueError(f"{n} states need as many non-negative seeds, got {seed!r}")
        return reseeded(state, seeds)

    # ------------------------------------------------------------------ bridge
    @property
    def bridge(self) -> HighwayBridge:
        """The converter to and from HighwayEnv states (built on first use)."""
        if self._bridge is None:
            bridge = self._model.bridge
            self._bridge = bridge(self.scenario, self.overrides, self.params.num_vehicles)
        return self._bridge

    def state_from_highway(self, states: TensorDictBase) -> TensorDict:
        """HighwayEnv states (``[M]``, or one) as tensor states ``[M]`` of this env.

        Values are read in float64 and cast to this env's dtype (exact in float64). The
        highway-env generator words and reset seed travel inside the tensor state, so
        that :meth:`state_to_highway` gives the same HighwayEnv states back.

        Raises:
            SnapshotError: a state of another scenario or config.
        """
        states = states.unsqueeze(0) if states.batch_dims == 0 else states
        return import_states(self.bridge, states, self.dtype, self.fingerprint).to(self.device)

    def state_to_highway(self, state: TensorDictBase) -> TensorDict:
        """Tensor states ``[M]`` as HighwayEnv states ``[M]``.

        HighwayEnv restores, continues and renders them; float values are written as
        they are (a float32 world as its float64 values).
        """
        return export_states(self.bridge, state)

    def render_frames(self, state: TensorDictBase) -> list:
        """highway-env's own rendering of each world of ``state`` (``[M]``): RGB arrays."""
        frames = []
        for highway_state in self.state_to_highway(state).unbind(0):
            self.bridge.renderer.set_state(highway_state)
            frames.append(self.bridge.renderer.render())
        return frames

    # ------------------------------------------------------------------ EnvBase
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDict:
        rows = torch.ones(self.batch_size, dtype=torch.bool, device=self.device)
        if tensordict is not None and "_reset" in tensordict.keys():
            rows = tensordict.get("_reset").reshape(self.batch_size)
        if kwargs.get("set_state"):
            if tensordict is None or STATE_KEY not in tensordict.keys():
                raise SnapshotError(
                    f"reset(set_state=True) needs a tensordict holding a {STATE_KEY!r} entry "
                    "(from env.get_state()); none was given"
                )
            state = tensordict.get(STATE_KEY)
            self.validate_state(state)  # before anything changes: the env stays usable
            self._world = where_rows(rows, world_from_tensordict(state), self._world)
            self._highway_rng = torch.where(
                rows.unsqueeze(-1), state.get(("highway", "rng")), self._highway_rng
            )
            self._highway_seed = torch.where(
                rows, state.get(("highway", "seed")), self._highway_seed
            )
        else:
            self._world, self._highway_rng, self._highway_seed = self._mode.fresh(
                self._world, rows, self._highway_rng, self._highway_seed
            )
        out = self._output(self._mode.observe(self._world))
        zero_fresh_rewards(out, self._world.steps, self._model.components)
        flag = torch.zeros((*self.batch_size, 1), dtype=torch.bool, device=self.device)
        out.update({"done": flag, "terminated": flag.clone(), "truncated": flag.clone()})
        out.set(STATE_KEY, self.get_state())
        return out

    def _step(self, tensordict: TensorDictBase) -> TensorDict:
        action = tensordict.get("action")
        # Partial steps: rows outside "_step" keep their world (one batched step anyway).
        rows = tensordict.get("_step", None)
        if self.check_actions:
            # Before anything changes, so that a refused action leaves the env as it was.
            check_action(action, self._action_leaf, self._name, batch_dims=1, rows=rows)
        if not self._categorical:
            action = action.argmax(-1)
        action, words = action.to(torch.int64), self._highway_rng
        if self._model.spawns:  # intersection-v0 spawns from highway-env's generator
            world, outputs, words = self._mode.step(self._world, action, words)
        else:
            world, outputs = self._mode.step(self._world, action)
        self.world_steps += self.batch_size[0]
        if rows is not None:
            rows = rows.reshape(self.batch_size)
            world = where_rows(rows, world, self._world)
            words = torch.where(rows.unsqueeze(-1), words, self._highway_rng)
        self._world, self._highway_rng = world, words
        out = self._output(outputs)
        terminated = outputs["terminated"].unsqueeze(-1)
        truncated = outputs["truncated"].unsqueeze(-1)
        out.set("reward", outputs["reward"].to(self.dtype).unsqueeze(-1))
        out.update(
            {"done": terminated | truncated, "terminated": terminated, "truncated": truncated}
        )
        if self.return_state:
            out.set(STATE_KEY, self.get_state())
        return out

    def _output(self, outputs: dict) -> TensorDict:
        return output_tensordict(outputs, self.batch_size, self.dtype, self.device)

    def _set_seed(self, seed: int | None) -> None:
        rows = torch.arange(self.batch_size[0], device=self.device)
        keys = seed_keys(rows, 0 if seed is None else int(seed))
        self._world = self._world._replace(rng_key=keys, rng_counter=torch.zeros_like(keys))
        if self._model.seed_words is not None:
            words, seeds = self._model.seed_words(self.batch_size[0], 0 if seed is None else seed)
            self._highway_rng, self._highway_seed = words.to(self.device), seeds.to(self.device)
