"""Corrupt highway-env states column by column, and restore them in a warm worker process.

A case names one entry of a state (a leaf, or one column of a packed entity table), a
corruption (zero, NaN, inf, sign flip, bit flip, truncation) and the scenario. The
worker restores the corrupted state and, when it is accepted, steps it, resets and
steps again. The worker runs in its own process under a timeout, so that a state
that hangs the simulator (a zeroed generator spins forever in numpy) is reported as
a hang and the worker is replaced, instead of hanging the test run.
"""

from __future__ import annotations

import math
import multiprocessing as mp
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase

from torchrl_grpo.envs import HighwayEnv, SnapshotError

WARMUP_STEPS = 3
STEPS_AFTER_RESTORE = 3

# bits flipped in a float64 (stored as int64), a float32 / int32, an int16, an int64
FLOAT64_BITS = (63, 62, 58, 52, 30)
FLOAT32_BITS = (31, 30, 26, 23, 10)
INT16_BITS = (15, 8, 1, 0)
INT64_BITS = (63, 40, 1, 0)


@dataclass(frozen=True)
class Case:
    """One corruption of one entry of a scenario's state.

    ``key`` is the leaf's key in the state; ``columns`` the column range of a packed
    entity table (``None``: the whole leaf); ``name`` the entry an error should name.
    """

    scenario: str
    key: tuple[str, ...]
    columns: tuple[int, int] | None
    name: str
    mode: str
    arg: int = 0
    is_float: bool = False

    def __str__(self) -> str:
        where = f"[{self.columns[0]}:{self.columns[1]}]" if self.columns else ""
        return (
            f"{self.scenario}:{'.'.join(self.key)}{where}({self.name}):{self.mode}{self.arg or ''}"
        )


def make_env(scenario: str) -> HighwayEnv:
    """The scenario a few steps after a seeded reset (steps with the zero action)."""
    env = HighwayEnv(scenario, seed=0)
    env.reset()
    for _ in range(WARMUP_STEPS):
        if env.step(_act(env))["next", "done"].any():
            break
    return env


def _act(env: HighwayEnv) -> TensorDictBase:
    return TensorDict(action=env.action_spec.zero())


def float_leaves(env: HighwayEnv) -> dict[tuple[str, ...], torch.dtype]:
    """The leaves of a state stored as bit patterns, with their float dtype."""
    out = {}
    for key in env.codec._float_keys:
        out[("sim", *key.split("."))] = torch.float64
    for key, dtype in env._output_floats.items():
        out[("output", *(key if isinstance(key, tuple) else (key,)))] = dtype
    return out


def column_names(env: HighwayEnv) -> dict[tuple[str, int], str]:
    """``(block, column) -> field name`` of every column of the packed entity tables."""
    layout = env.codec.layout
    names = {("i16", 0): "kind", ("i16", 1): "class"}
    for name, c in layout.columns.items():
        for j in range(c.start, c.stop):
            names[(c.block, j)] = name.split("#")[0]
    for j, name in enumerate(layout.names):
        names[("flags", layout.present.start + j)] = name
        names[("flags", layout.is_none.start + j)] = name
    return names


def _modes(dtype: torch.dtype, is_float: bool) -> list[tuple[str, int]]:
    if dtype == torch.bool:
        return [("zero", 0), ("flip", 0), ("ones", 0)]
    if is_float:
        bits = FLOAT64_BITS if dtype == torch.int64 else FLOAT32_BITS
        return [
            ("zero", 0),
            ("nan", 0),
            ("inf", 0),
            ("neginf", 0),
            ("sign", 0),
            *(("bit", b) for b in bits),
        ]
    bits = {torch.int16: INT16_BITS, torch.int64: INT64_BITS}.get(dtype, (7, 0))
    return [("zero", 0), ("sign", 0), ("max", 0), ("min", 0), *(("bit", b) for b in bits)]


def cases(env: HighwayEnv, scenario: str, truncation: bool = True) -> list[Case]:
    """Every corruption of every entry (each packed column on its own) of ``env``'s state."""
    state = env.get_state()
    floats = float_leaves(env)
    names = column_names(env)
    out = []
    for key in state.keys(True, True):
        key = key if isinstance(key, tuple) else (key,)
        leaf = state[key]
        is_float = key in floats
        packed = key[:2] == ("sim", "entities")
        if packed:
            block = key[2]
            for j in range(leaf.shape[-1]):
                name = names[(block, j)]
                for mode, arg in _modes(leaf.dtype, block == "f64"):
                    out.append(Case(scenario, key, (j, j + 1), name, mode, arg, block == "f64"))
        else:
            name = ".".join(key[1:])
            for mode, arg in _modes(leaf.dtype, is_float):
                out.append(Case(scenario, key, None, name, mode, arg, is_float))
        if truncation:
            name = ".".join(key[1:])
            out.append(Case(scenario, key, None, name, "delete"))
            if leaf.ndim:
                out.append(Case(scenario, key, None, name, "shorten"))
    return out


def corrupt(state: TensorDictBase, case: Case) -> TensorDictBase:
    """A corrupted copy of ``state`` (``state`` is untouched)."""
    broken = state.apply(lambda t: t.clone())  # integer leaves: a faithful copy
    if case.mode == "delete":
        del broken[case.key]
        return broken
    leaf = broken[case.key]
    if case.mode == "shorten":
        broken[case.key] = leaf[..., :-1].clone() if leaf.shape[-1] else leaf.reshape(-1)[:0]
        return broken
    view = leaf if case.columns is None else leaf[..., case.columns[0] : case.columns[1]]
    if view.dtype == torch.bool:
        if case.mode == "zero":
            view.fill_(False)
        elif case.mode == "ones":
            view.fill_(True)
        else:
            view.copy_(~view)
        return broken
    if case.is_float:
        ftype = {torch.int64: torch.float64, torch.int32: torch.float32}[view.dtype]
        as_float = view.view(ftype)
        special = {"zero": 0.0, "nan": math.nan, "inf": math.inf, "neginf": -math.inf}
        if case.mode in special:
            as_float.fill_(special[case.mode])
        elif case.mode == "sign":
            as_float.neg_()
        else:
            _flip_bit(view, case.arg)
        return broken
    info = torch.iinfo(view.dtype)
    if case.mode == "zero":
        view.fill_(0)
    elif case.mode == "sign":
        view.copy_(-view)
    elif case.mode == "max":
        view.fill_(info.max)
    elif case.mode == "min":
        view.fill_(info.min)
    else:
        _flip_bit(view, case.arg)
    return broken


def _flip_bit(view: torch.Tensor, bit: int) -> None:
    width = torch.iinfo(view.dtype).bits
    mask = torch.tensor(1, dtype=torch.int64) << bit
    if bit == width - 1:
        mask = torch.tensor(torch.iinfo(view.dtype).min, dtype=torch.int64)
    view.bitwise_xor_(mask.to(view.dtype))


def run_case(env: HighwayEnv, state: TensorDictBase, case: Case) -> tuple[str, str]:
    """``("refused", message)``, ``("ok", "")`` or ``("broken", what went wrong)``."""
    broken = corrupt(state, case)
    try:
        env.validate_state(broken)
        valid = True
    except SnapshotError:
        valid = False
    except Exception as err:  # noqa: BLE001 - the point of the harness
        return "broken", f"validate_state raised {type(err).__name__}: {err}"
    try:
        env.set_state(broken)
    except SnapshotError as err:
        if valid:
            return "broken", f"validate_state accepted it, restore refused it: {err}"
        return "refused", str(err)
    except Exception as err:  # noqa: BLE001
        return "broken", f"restore raised {type(err).__name__}: {err}"
    if not valid:
        return "broken", "validate_state refused it, restore accepted it"
    try:
        for _ in range(STEPS_AFTER_RESTORE):
            td = env.step(_act(env))
            _check_finite(td["next"])
            if td["next", "done"].any():
                break
        _check_finite(env.reset())
        _check_finite(env.step(_act(env))["next"])
    except Exception as err:  # noqa: BLE001
        return "broken", f"stepping the restored state raised {type(err).__name__}: {err}"
    return "ok", ""


def _check_finite(td: TensorDictBase) -> None:
    for key, value in td.items(True, True):
        name = key if isinstance(key, str) else key[0]
        if name in ("state", "reward_components"):
            continue
        if value.dtype.is_floating_point and not torch.isfinite(value).all():
            raise ValueError(f"{key} is not finite: {value}")


def _serve(conn: Any) -> None:
    envs: dict[str, tuple[HighwayEnv, TensorDictBase]] = {}
    while True:
        case = conn.recv()
        if case is None:
            return
        if case.scenario not in envs:
            env = make_env(case.scenario)
            envs[case.scenario] = (env, env.get_state())
        env, state = envs[case.scenario]
        result = run_case(env, state, case)
        try:
            env.set_state(state)
        except Exception as err:  # noqa: BLE001
            result = ("broken", f"{result[1]}; the clean state no longer restores: {err}")
            del envs[case.scenario]
        conn.send(result)


class WarmWorker:
    """One process that runs cases; replaced when a case outlives ``timeout`` seconds."""

    def __init__(self, timeout: float = 20.0) -> None:
        self.timeout = timeout
        self.restarts = 0
        self._ctx = mp.get_context("spawn")
        self._start()

    def _start(self) -> None:
        self._warm: set[str] = set()
        self._conn, child = self._ctx.Pipe()
        self._proc = self._ctx.Process(target=_serve, args=(child,), daemon=True)
        self._proc.start()
        child.close()

    def run(self, case: Case, timeout: float | None = None) -> tuple[str, str]:
        """The case's outcome, ``("hang", ...)`` after the timeout, ``("died", ...)``."""
        if case.scenario not in self._warm:
            timeout = max(timeout or self.timeout, 120.0)  # imports and the env's build
            self._warm.add(case.scenario)
        self._conn.send(case)
        if not self._conn.poll(timeout or self.timeout):
            self._proc.kill()
            self._proc.join()
            self.restarts += 1
            self._start()
            return "hang", f"no answer within {timeout or self.timeout} s"
        try:
            return self._conn.recv()
        except EOFError:
            self._proc.join()
            self.restarts += 1
            self._start()
            return "died", f"the worker died (exit code {self._proc.exitcode})"

    def close(self) -> None:
        try:
            self._conn.send(None)
        except (BrokenPipeError, OSError):
            pass
        self._proc.join(5)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join()
