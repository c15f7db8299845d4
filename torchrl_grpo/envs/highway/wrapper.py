"""HighwayEnv: a TorchRL env over highway-env whose complete state is a TensorDict."""

from __future__ import annotations

import difflib
from typing import Any

import gymnasium as gym
import highway_env  # noqa: F401 - registers the scenarios with gymnasium
import torch
from tensordict import TensorDictBase
from torchrl.data import Categorical, Composite, TensorSpec, Unbounded

from torchrl_grpo.envs.core.bits import flag_tensor, float32_tensor
from torchrl_grpo.envs.core.snapshot_env import SnapshotEnv
from torchrl_grpo.envs.highway import schema
from torchrl_grpo.envs.highway.fast_observation import use_fast_kinematics
from torchrl_grpo.envs.highway.highway_codec import HIGHWAY_SCENARIOS, HighwayStateCodec


class HighwayEnv(SnapshotEnv):
    """A highway-env scenario as a TorchRL env with exact snapshots.

    Besides the scenario's observation (``"observation"``, or the goal keys of
    parking-v0), every output carries what users plot and log, as tensors:
    ``crashed``, ``on_road``, ``speed`` (m/s), ``ego_position`` (x, y in m),
    ``ego_heading`` (rad) and, where the scenario reports them, each reward
    component under ``("reward_components", name)``.

    Args:
        scenario: one of :data:`~torchrl_grpo.envs.HIGHWAY_SCENARIOS`.
        config: overrides of the scenario's default config (checked: an unknown
            top-level key is an error, not silently ignored).
        seed: seeds the first episode.
        return_state: write the post-step state into every step's output.
        render_mode: ``"rgb_array"`` for frames (works headless).
        max_vehicles: state padding for ``road.vehicles`` (default: count + 16).
        max_objects: state padding for ``road.objects`` (default: count + 4).
        categorical_action_encoding: discrete actions as integer indices.
        device: the device of the output tensors.
        fast_observation: compute a plain Kinematics observation without pandas
            (:class:`~torchrl_grpo.envs.highway.fast_observation.FastKinematicObservation`:
            the same bits, 3 ms less per step); ``False`` keeps highway-env's own.
        check_actions: refuse an action outside the action spec before highway-env
            sees it (see :class:`~torchrl_grpo.envs.SnapshotEnv`).

    Bit-exactness holds on one machine and numeric setup: restore + the same actions
    gives the same bits, as highway-env itself would; on another CPU (another BLAS
    kernel) curved-lane scenarios may evolve differently from the same state.

    Example:
        >>> from torchrl.envs.utils import check_env_specs
        >>> from tensordict import TensorDict
        >>> env = HighwayEnv("merge-v0", seed=0)
        >>> check_env_specs(env)
        >>> _ = env.reset()
        >>> state = env.get_state()
        >>> idle = TensorDict(action=torch.tensor(1))
        >>> a = [env.step(idle.clone())["next", "ego_position"] for _ in range(3)]
        >>> _ = env.reset(TensorDict(state=state), set_state=True)
        >>> b = [env.step(idle.clone())["next", "ego_position"] for _ in range(3)]
        >>> all(torch.equal(x, y) for x, y in zip(a, b))
        True
    """

    # highway-env reports no value for a reward component some steps: NaN stands for it.
    nan_outputs = frozenset({"reward_components"})

    def __init__(
        self,
        scenario: str = "highway-fast-v0",
        config: dict | None = None,
        *,
        seed: int | None = None,
        return_state: bool = False,
        render_mode: str | None = None,
        max_vehicles: int | None = None,
        max_objects: int | None = None,
        categorical_action_encoding: bool = True,
        device: torch.device | str = "cpu",
        fast_observation: bool = True,
        check_actions: bool = True,
    ) -> None:
        if scenario not in HIGHWAY_SCENARIOS:
            close = difflib.get_close_matches(scenario, HIGHWAY_SCENARIOS, n=3)
            hint = f" Did you mean {close}?" if close else ""
            raise ValueError(
                f"unknown highway-env scenario {scenario!r}.{hint} "
                f"Known scenarios: {list(HIGHWAY_SCENARIOS)}"
            )
        self.scenario = scenario
        self.fast_observation = bool(fast_observation)
        config = dict(config or {})
        _check_config_keys(scenario, config)
        self._param_keys = list(schema.CLASS_PARAMETERS)
        self._class_params: list[float] = []
        env = gym.make(scenario, config=config, disable_env_checker=True)
        # Set after construction: lane-keeping-v0's constructor takes no render_mode.
        env.unwrapped.render_mode = render_mode
        super().__init__(
            env,
            HighwayStateCodec(max_vehicles=max_vehicles, max_objects=max_objects),
            seed=seed,
            return_state=return_state,
            categorical_action_encoding=categorical_action_encoding,
            device=device,
            check_actions=check_actions,
        )

    @property
    def config(self) -> dict:
        """The scenario's full config, as highway-env holds it."""
        return self._env.unwrapped.config

    # ------------------------------------------------------------------ info
    def _info_spec(self, info: dict) -> dict[Any, TensorSpec]:
        self._reward_components = list(info.get("rewards", {}))
        self._has_success = "is_success" in info
        flag = Categorical(2, (1,), dtype=torch.bool, device=self.device)
        spec: dict[Any, TensorSpec] = {
            "crashed": flag.clone(),
            "on_road": flag.clone(),
            "speed": Unbounded((1,), dtype=torch.float32, device=self.device),
            "ego_position": Unbounded((2,), dtype=torch.float32, device=self.device),
            "ego_heading": Unbounded((1,), dtype=torch.float32, device=self.device),
        }
        if self._has_success:
            spec["is_success"] = flag.clone()
        if self._reward_components:
            spec["reward_components"] = Composite(
                {
                    name: Unbounded((1,), dtype=torch.float32, device=self.device)
                    for name in self._reward_components
                },
                device=self.device,
            )
        return spec

    def _read_info(self, info: dict) -> dict[Any, torch.Tensor]:
        # Read from the vehicle, not from info: lane-keeping-v0's step info is empty.
        ego = self._env.unwrapped.vehicle
        out: dict[Any, torch.Tensor] = {
            "crashed": flag_tensor(ego.crashed),
            "on_road": flag_tensor(ego.on_road),
            "speed": float32_tensor([ego.speed]),
            "ego_position": float32_tensor(ego.position),
            "ego_heading": float32_tensor([ego.heading]),
        }
        if self._has_success:
            out["is_success"] = flag_tensor(info.get("is_success", False))
        if self._reward_components:
            rewards = info.get("rewards", {})
            out["reward_components"] = {
                name: float32_tensor([rewards.get(name, float("nan"))])
                for name in self._reward_components
            }
        return out

    # ------------------------------------------------------------------ class parameters
    def _gym_reset(self, seed: int | None) -> tuple[Any, dict]:
        # A fresh episode starts from the classes' own constants, not from whatever
        # another scenario in this process wrote onto them (intersection-v0 does).
        for (cls, name), value in schema.PRISTINE_CLASS_PARAMETERS.items():
            setattr(cls, name, value)
        obs, info = super()._gym_reset(seed)
        self._remember_class_params()
        if "rewards" in info:
            # highway-env computes reset-time reward components for an action sampled from
            # an unseeded, freshly rebuilt action space: no action was taken yet, so 0.
            info = {**info, "rewards": dict.fromkeys(info["rewards"], 0.0)}
        return obs, info

    def refresh_output(self) -> None:
        """Recompute the output from the simulator as it stands, after its objects were edited.

        The observation, flags and reward components the env reports (and that
        :meth:`get_state` stores and a restore returns) are read again from highway-env's
        objects. For code that writes a world into highway-env by hand, as the tensor
        simulator's bridge does. A world at step 0 reports zero reward components, as a
        fresh reset does. Observing draws from the simulator's generator with a shuffled
        Kinematics order, so the bridge is for the sorted order only.

        Example:
            >>> env = HighwayEnv("highway-fast-v0", seed=0)
            >>> env.gym_env.unwrapped.vehicle.speed = 20.0
            >>> env.refresh_output()
            >>> float(env.get_state()["output", "speed"].view(torch.float32))
            20.0
        """
        core = self._env.unwrapped
        obs = core.observation_type.observe()
        info = core._info(obs, None)
        if core.steps == 0 and "rewards" in info:
            info = {**info, "rewards": dict.fromkeys(info["rewards"], 0.0)}
        self._last_output = self._output_leaves(obs, info)

    def _remember_class_params(self) -> None:
        self._class_params = [getattr(c, n) for c, n in self._param_keys]

    def _restore(self, tensordict: TensorDictBase | None):
        output = super()._restore(tensordict)
        self._remember_class_params()
        return output

    def _apply_class_params(self) -> None:
        # Envs of several scenarios may share this process: put back this env's values
        # of the process-global class constants before simulating or snapshotting.
        for (cls, name), value in zip(self._param_keys, self._class_params, strict=True):
            if getattr(cls, name) != value:
                setattr(cls, name, value)

    def _step(self, tensordict: TensorDictBase):
        self._apply_class_params()
        if self.fast_observation:
            # Every reset rebuilds highway-env's observation object: swap it again.
            use_fast_kinematics(self._env.unwrapped)
        return super()._step(tensordict)

    def get_state(self):
        """See :meth:`SnapshotEnv.get_state`; the state holds this env's class constants."""
        self._apply_class_params()
        return super().get_state()


def _check_config_keys(scenario: str, config: dict) -> None:
    if not config:
        return
    defaults = gym.spec(scenario).entry_point
    module_name, class_name = defaults.split(":")
    module = __import__(module_name, fromlist=[class_name])
    known = getattr(module, class_name).default_config()
    unknown = sorted(set(config) - set(known))
    if unknown:
        hints = {k: difflib.get_close_matches(k, known, n=1) for k in unknown}
        raise ValueError(
            f"unknown config keys for {scenario}: "
            + ", ".join(
                f"{k!r}" + (f" (did you mean {h[0]!r}?)" if h else "") for k, h in hints.items()
            )
        )
