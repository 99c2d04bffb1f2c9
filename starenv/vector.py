"""A vector env for many star-sensor envs on a few cores.

``SharedMemoryVectorEnv`` runs ``num_envs`` envs in ``workers`` processes, each stepping its share of the envs one
after the other.  Everything of fixed shape -- actions, observations, rewards, termination and truncation flags --
lives in shared memory that the main process and the workers read and write in place; a step sends each worker one
short command and gets back one short answer.  Infos (truth and scores, of varying length) are pickled through the
pipes only when asked for (``infos=True``, the default); a rollout that needs only the frames and the gyro can turn
them off, and take the observations as views of the shared memory (``copy=False``), and then pays little per step
beyond the envs' own work.

Gymnasium's ``AsyncVectorEnv`` sends every action through a pipe, copies each observation into shared memory, sends
every info back and merges them: its main process's share of each step idles the workers.  ``benchmarks/env_speed.py``
prints both speed-ups over one env.  Episodes reset automatically as in Gymnasium's default ("next step"
mode): the step after an episode ends returns the first observation of the next episode, with reward 0, no flags and
the reset's info.

An exception in a worker's env is raised again in the main process with the env's index and message (a ValueError
for a NaN in an action stays a ValueError), after every worker has answered, so the pipes stay in step (the envs
before the failing one in its worker's share have taken the step, those after it have not).  A worker that dies
(before or during a command) raises a RuntimeError naming its envs; one that does not answer within ``timeout_s``
(stopped, or stuck in an env) raises a TimeoutError naming its envs.  After either the vector env cannot go on (its
workers are out of step): every later reset or step raises that error again, and ``close`` ends the workers.

    envs = SharedMemoryVectorEnv.from_id("StarEnv/Paper000-v0", num_envs=4, workers=2, infos=False)
    observations, infos = envs.reset(seed=0)      # env i is seeded seed + i
    observations, rewards, terminations, truncations, infos = envs.step(actions)

It is what ``gym.make_vec`` builds for a StarEnv id when given no ``vectorization_mode`` (every id registers
:func:`make_vector_env` as its vector entry point): ``gym.make_vec("StarEnv/Paper000-v0", num_envs=4, workers=2)``.
``vectorization_mode="sync"`` or ``"async"`` gives Gymnasium's own vector envs, with the same results bit for bit.
"""

from __future__ import annotations

import builtins
import multiprocessing
import traceback
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector.utils import (
    batch_space,
    create_shared_memory,
    read_from_shared_memory,
    write_to_shared_memory,
)
from gymnasium.vector.vector_env import AutoresetMode

from starenv.parallel import usable_cores

__all__ = ["SharedMemoryVectorEnv", "make_vector_env"]


def _index(tree, i: int):
    """Env ``i``'s entry (a copy) of a batched array or a dict / tuple of them."""
    if isinstance(tree, dict):
        return {key: _index(value, i) for key, value in tree.items()}
    if isinstance(tree, tuple):
        return tuple(_index(value, i) for value in tree)
    return np.array(tree[i])


def _assign(views, values, name: str = "actions") -> None:
    """Copy a batch (array, dict or tuple of them) into shared-memory views of the same structure."""
    if isinstance(views, dict):
        if not isinstance(values, dict) or set(values) != set(views):
            got = sorted(values) if isinstance(values, dict) else type(values).__name__
            raise ValueError(f"{name} must be a dict with keys {sorted(views)}, got {got}")
        for key, view in views.items():
            _assign(view, values[key], f"{name}[{key!r}]")
    elif isinstance(views, tuple):
        if not isinstance(values, tuple) or len(values) != len(views):
            raise ValueError(f"{name} must be a tuple of {len(views)} batches")
        for k, (view, value) in enumerate(zip(views, values, strict=True)):
            _assign(view, value, f"{name}[{k}]")
    else:
        value = np.asarray(values)
        if value.shape != views.shape:
            raise ValueError(f"{name} must have shape {views.shape} (num_envs first), got {value.shape}")
        views[...] = value


def _copy(tree):
    """A copy of an array or a dict / tuple of them."""
    if isinstance(tree, dict):
        return {key: _copy(value) for key, value in tree.items()}
    if isinstance(tree, tuple):
        return tuple(_copy(value) for value in tree)
    return tree.copy()


class _Shared:
    """The shared-memory blocks of a vector env and numpy views of them."""

    def __init__(self, observation_space, action_space, num_envs: int, context):
        self.observation_space, self.action_space = observation_space, action_space
        self.num_envs = num_envs
        self.observation_block = create_shared_memory(observation_space, num_envs, context)
        self.action_block = create_shared_memory(action_space, num_envs, context)
        self.reward_block = context.Array("d", num_envs, lock=False)
        self.flag_block = context.Array("b", 2 * num_envs, lock=False)
        self.views()

    def views(self) -> None:
        self.observations = read_from_shared_memory(self.observation_space, self.observation_block, self.num_envs)
        self.actions = read_from_shared_memory(self.action_space, self.action_block, self.num_envs)
        self.rewards = np.frombuffer(self.reward_block, np.float64)
        flags = np.frombuffer(self.flag_block, np.int8).reshape(2, self.num_envs)
        self.terminations, self.truncations = flags[0], flags[1]

    def __getstate__(self) -> dict:
        return {key: value for key, value in self.__dict__.items()
                if key in ("observation_space", "action_space", "num_envs", "observation_block", "action_block",
                           "reward_block", "flag_block")}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self.views()


def _worker(env_fns: list[Callable[[], gym.Env]], first: int, shared: _Shared, pipe, parent_pipe) -> None:
    """Step envs ``first``, ``first + 1``, ... on the main process's commands (see ``SharedMemoryVectorEnv``)."""
    parent_pipe.close()
    envs: list[gym.Env] = []
    ending = [False] * len(env_fns)  # the env's last step ended its episode: the next step resets it
    try:
        envs = [fn() for fn in env_fns]
        pipe.send(("ok", None))
    except Exception as error:  # noqa: BLE001  (sent to the main process, raised there)
        pipe.send(("error", (first, type(error).__name__, str(error), traceback.format_exc())))
        return
    while True:
        try:
            command, data = pipe.recv()
        except EOFError:  # the main process is gone: close the envs (files their wrappers write are finished)
            command, data = "close", None
        if command == "close":
            for env in envs:
                env.close()
            try:
                pipe.send(("ok", None))
            except (BrokenPipeError, ConnectionResetError):  # nobody to tell
                pass
            break
        infos = []
        k = 0
        try:
            for k, env in enumerate(envs):
                i = first + k
                if command == "reset":
                    seeds, options = data
                    observation, info = env.reset(seed=seeds[k], options=options)
                    reward, terminated, truncated = 0.0, False, False
                elif ending[k]:
                    observation, info = env.reset()
                    reward, terminated, truncated = 0.0, False, False
                else:
                    observation, reward, terminated, truncated, info = env.step(_index(shared.actions, i))
                ending[k] = bool(terminated or truncated)
                write_to_shared_memory(shared.observation_space, i, observation, shared.observation_block)
                shared.rewards[i] = reward
                shared.terminations[i], shared.truncations[i] = terminated, truncated
                infos.append(info)
            pipe.send(("ok", infos if command == "reset" or data else None))
        except Exception as error:  # noqa: BLE001  (sent to the main process, raised there)
            pipe.send(("error", (first + k, type(error).__name__, str(error), traceback.format_exc())))


def _workers(num_envs: int, workers: int | None) -> int | None:
    """The worker processes of ``num_envs`` envs: ``workers``, or by default one per env up to the number of CPUs."""
    return min(num_envs, multiprocessing.cpu_count()) if workers is None else workers


class SharedMemoryVectorEnv(gym.vector.VectorEnv):
    """``num_envs`` envs stepped by ``workers`` processes through shared memory (see the module docstring).

    Args:
        env_fns: one callable per env that builds it (pickled to the workers unless the context forks).
        workers: processes to run them in (default: one per env up to the number of CPUs), each a contiguous share
            of the envs, the shares as even as they can be (``numpy.array_split``).
        infos: send each env's info back on every step (reset always does).
        copy: return copies of the observations (else views of the shared memory, overwritten by the next step).
        context: the multiprocessing start method (default: the platform's).
        timeout_s: longest wait (s) for the workers' answers to one reset or step (None: no limit); building the
            envs at construction has the same limit.
    """

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, env_fns: Sequence[Callable[[], gym.Env]], *, workers: int | None = None,
                 infos: bool = True, copy: bool = True, context: str | None = None,
                 timeout_s: float | None = 600.0):
        self._pipes, self._processes = [], []  # nothing to close yet
        self._broken: Exception | None = None
        if timeout_s is not None and not (isinstance(timeout_s, int | float) and timeout_s > 0):
            raise ValueError(f"timeout_s must be a positive number of seconds or None, got {timeout_s!r}")
        self.timeout_s = timeout_s
        if len(env_fns) == 0:
            raise ValueError("env_fns must hold at least one env constructor")
        for name, flag in (("infos", infos), ("copy", copy)):
            if not isinstance(flag, bool):
                raise ValueError(f"{name} must be True or False, got {flag!r}")
        self.num_envs = len(env_fns)
        workers = _workers(self.num_envs, workers)
        if not isinstance(workers, int) or isinstance(workers, bool) or not 1 <= workers <= self.num_envs:
            raise ValueError(f"workers must be an integer from 1 to num_envs ({self.num_envs}), got {workers!r}")
        self.env_fns, self.infos, self.copy = list(env_fns), infos, copy

        probe = self.env_fns[0]()
        self.single_observation_space, self.single_action_space = probe.observation_space, probe.action_space
        self.spec, self.render_mode = probe.spec, probe.render_mode
        self.metadata = {**probe.metadata, "autoreset_mode": AutoresetMode.NEXT_STEP}
        probe.close()
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)

        mp = multiprocessing.get_context(context)
        self._shared = _Shared(self.single_observation_space, self.single_action_space, self.num_envs, mp)
        self._shares = [[int(i) for i in share] for share in np.array_split(np.arange(self.num_envs), workers)]
        self.closed = False
        for share in self._shares:
            parent, child = mp.Pipe()
            process = mp.Process(target=_worker, name=f"starenv-vector-{share[0]}", daemon=True,
                                 args=([self.env_fns[i] for i in share], share[0], self._shared, child, parent))
            process.start()
            child.close()
            self._pipes.append(parent)
            self._processes.append(process)
        try:
            self._answers()  # every env built
        except Exception:
            self.close()
            raise

    @classmethod
    def from_id(cls, env_id: str, num_envs: int, *, workers: int | None = None, infos: bool = True,
                copy: bool = True, context: str | None = None, timeout_s: float | None = 600.0,
                **env_kwargs) -> SharedMemoryVectorEnv:
        """``num_envs`` copies of ``gym.make(env_id, **env_kwargs)``.  ``env_id`` is a registered id such as
        ``"StarEnv/Paper000-v0"``; ``gym.make`` imports the module of a ``"module:Env"`` id, so do not pass ids read
        from untrusted files.  Unless ``env_kwargs`` sets it, each env draws its noise on a second thread
        (``noise_thread``) where this process may use two cores for every worker
        (:func:`~starenv.parallel.usable_cores`), and on its worker's own thread otherwise (the same results bit for
        bit)."""
        if not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        if "noise_thread" not in env_kwargs and (workers is None or isinstance(workers, int)):
            env_kwargs["noise_thread"] = usable_cores() >= 2 * _workers(num_envs, workers)
        return cls([_Maker(env_id, env_kwargs)] * num_envs, workers=workers, infos=infos, copy=copy,
                   context=context, timeout_s=timeout_s)

    def reset(self, *, seed: int | Sequence[int | None] | None = None, options: dict | None = None):
        """Reset every env; an integer ``seed`` seeds env ``i`` with ``seed + i``."""
        if seed is None or isinstance(seed, int | np.integer):
            seeds = [None if seed is None else int(seed) + i for i in range(self.num_envs)]
        else:
            seeds = list(seed)
            if len(seeds) != self.num_envs:
                raise ValueError(f"seed must be an integer, None or {self.num_envs} of them, got {len(seeds)}")
        self._send([("reset", ([seeds[i] for i in share], options)) for share in self._shares])
        infos = self._merged(self._answers())
        return self._observations(), infos

    def step(self, actions):
        """Step every env with its row of ``actions`` (a batch of the action space, ``num_envs`` first)."""
        if self._broken is not None:  # before the actions are written: a worker may still be reading them
            raise self._broken
        _assign(self._shared.actions, actions)
        self._send([("step", self.infos)] * len(self._pipes))
        infos = self._merged(self._answers())  # empty unless self.infos
        return (self._observations(), self._shared.rewards.copy(), self._shared.terminations.astype(bool),
                self._shared.truncations.astype(bool), infos)

    def close_extras(self, **kwargs) -> None:
        """Close every env (files their wrappers write, such as videos, are finished) and end the workers (a worker
        that does not answer within ``timeout_s`` (at most 30 s), or after an error left the pipes out of step, is
        terminated)."""
        wait = 30.0 if self.timeout_s is None else min(30.0, self.timeout_s)
        for pipe, process in zip(self._pipes, self._processes, strict=True):
            if process.is_alive() and self._broken is None:
                try:
                    pipe.send(("close", None))
                    if pipe.poll(wait):
                        pipe.recv()
                except (BrokenPipeError, ConnectionResetError, EOFError):
                    pass
            if self._broken is not None and process.is_alive():
                process.kill()  # stopped or out of step: SIGKILL also ends a SIGSTOPped process
            process.join(timeout=wait)
            if process.is_alive():
                process.terminate()
            pipe.close()

    def _observations(self):
        return _copy(self._shared.observations) if self.copy else self._shared.observations

    def _send(self, commands: list) -> None:
        """One command to each worker; a worker gone (a broken pipe) is named as :meth:`_answers` names it."""
        if self._broken is not None:
            raise self._broken
        for pipe, process, share, command in zip(self._pipes, self._processes, self._shares, commands, strict=True):
            try:
                pipe.send(command)
            except (BrokenPipeError, ConnectionResetError, EOFError):
                process.join(timeout=5)
                self._broken = RuntimeError(f"env {share[0]}: the worker of envs {share[0]}-{share[-1]} died "
                                            f"(exit code {process.exitcode})")
                raise self._broken from None

    def _answers(self) -> list:
        """Each worker's answer, in env order; the first error is raised once every worker has answered (or was
        found dead, or let ``timeout_s`` pass: then the vector env is broken, see the module docstring)."""
        import time

        answers, error = [], None
        deadline = None if self.timeout_s is None else time.monotonic() + self.timeout_s
        for pipe, process, share in zip(self._pipes, self._processes, self._shares, strict=True):
            envs = f"envs {share[0]}-{share[-1]}"
            try:
                if deadline is not None and not pipe.poll(max(0.0, deadline - time.monotonic())):
                    self._broken = TimeoutError(f"env {share[0]}: the worker of {envs} did not answer within "
                                                f"{self.timeout_s:g} s (stopped or stuck)")
                    status, payload = "broken", None
                else:
                    status, payload = pipe.recv()
            except (EOFError, ConnectionResetError, BrokenPipeError):
                process.join(timeout=5)
                self._broken = RuntimeError(f"env {share[0]}: the worker of {envs} died (exit code "
                                            f"{process.exitcode})")
                status, payload = "broken", None
            if status == "broken":
                continue
            if status == "error":
                error = error or payload
            else:
                answers.extend(payload or [])
        if self._broken is not None:
            raise self._broken
        if error is not None:
            index, name, message, worker_traceback = error
            kind = getattr(builtins, name, None)
            if not (isinstance(kind, type) and issubclass(kind, Exception)):
                kind, message = RuntimeError, f"{name}: {message}"
            raise kind(f"env {index}: {message}") from (RuntimeError(worker_traceback) if worker_traceback else None)
        return answers

    def _merged(self, infos: list[dict]) -> dict:
        merged: dict = {}
        for i, info in enumerate(infos):
            merged = self._add_info(merged, info, i)
        return merged

    def __del__(self):
        if not getattr(self, "closed", True):
            self.close()


class _Maker:
    """A picklable ``gym.make(env_id, **kwargs)``."""

    def __init__(self, env_id: str, kwargs: dict[str, Any]):
        self.env_id, self.kwargs = env_id, dict(kwargs)

    def __call__(self) -> gym.Env:
        return gym.make(self.env_id, **self.kwargs)


VECTOR_OPTIONS = ("workers", "infos", "copy", "context", "timeout_s")  # SharedMemoryVectorEnv's own arguments


def make_vector_env(num_envs: int = 1, **kwargs) -> SharedMemoryVectorEnv:
    """The ``vector_entry_point`` of every StarEnv id: ``gym.make_vec(id, num_envs)`` without a
    ``vectorization_mode`` builds a :class:`SharedMemoryVectorEnv` of ``num_envs`` copies of the id's env.  The
    keyword arguments named in ``VECTOR_OPTIONS`` go to the vector env, the rest (the id's own ``scenario``,
    ``max_episode_steps``, ``overrides``, ...) to each env."""
    options = {key: kwargs.pop(key) for key in VECTOR_OPTIONS if key in kwargs}
    return SharedMemoryVectorEnv.from_id("StarEnv/Scenario-v0", num_envs, **options, **kwargs)
