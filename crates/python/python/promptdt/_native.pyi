"""Typed stubs of promptdt._native (the Rust extension module)."""
from os import PathLike
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
import numpy.typing as npt

_Path = Union[str, PathLike]
F32 = npt.NDArray[np.float32]

__version__: str
LIBTORCH_VERSION: str

def load_dataset(path: _Path) -> Dict[str, Any]: ...
def families() -> Dict[str, Dict[str, Any]]: ...
def task_params(family: str, task: int) -> str: ...
def train(
    out: _Path,
    config: Optional[_Path] = None,
    resume: bool = False,
    seed: Optional[int] = None,
    iterations: Optional[int] = None,
    method: Optional[str] = None,
    device: Optional[str] = None,
    data: Optional[_Path] = None,
    progress: Optional[Callable[[Dict[str, Any]], Any]] = None,
) -> Dict[str, Any]: ...
def evaluate(
    run_dir: _Path,
    episodes: Optional[int] = None,
    split: str = "test",
    device: Optional[str] = None,
    data: Optional[_Path] = None,
) -> str: ...
def experiments() -> str: ...
def is_scripted(family: str) -> bool: ...
def collect_scripted(
    family: str,
    out: _Path,
    seed: int = 0,
    episodes: Optional[int] = None,
    prompt_episodes: Optional[int] = None,
    action_noise: Optional[float] = None,
    progress: Optional[Callable[[Dict[str, Any]], Any]] = None,
) -> int: ...
def collect_from_agent(
    agent_dir: _Path,
    out: _Path,
    seed: int = 0,
    episodes: Optional[int] = None,
    prompt_episodes: Optional[int] = None,
    device: str = "cpu",
    progress: Optional[Callable[[Dict[str, Any]], Any]] = None,
) -> int: ...
def set_num_threads(threads: int) -> None: ...

class VecEnv:
    family: str
    tasks: List[int]
    obs_dim: int
    act_dim: int
    horizon: int
    num_envs: int
    def __init__(self, family: str, tasks: Sequence[int], threads: int = 0) -> None: ...
    def reset(self, seeds: Sequence[int], indices: Optional[Sequence[int]] = None) -> F32: ...
    def step(
        self, actions: npt.ArrayLike, mask: Optional[Sequence[bool]] = None
    ) -> Tuple[F32, F32, npt.NDArray[np.bool_], npt.NDArray[np.bool_]]: ...
    def last_success(self) -> Optional[npt.NDArray[np.bool_]]: ...

class Prompt:
    steps: int
    states: F32
    actions: F32
    returns_to_go: F32
    timesteps: npt.NDArray[np.int64]
    mask: F32

class TaskPlan:
    name: str
    index: int
    seeds: List[int]
    prompt: Optional[Prompt]

class Policy:
    obs_dim: int
    act_dim: int
    k: int
    method: str
    env: str
    uses_prompt: bool
    target_return: float
    rtg_scale: float
    max_ep_len: int
    iteration: int
    prompt_steps: int
    @staticmethod
    def load(
        run_dir: _Path, device: str = "cpu", data: Optional[_Path] = None, threads: Optional[int] = None
    ) -> "Policy": ...
    def prompt_tasks(self) -> List[int]: ...
    def task_prompt(self, task: int, seed: int = 0) -> Prompt: ...
    def prompt(
        self,
        states: npt.ArrayLike,
        actions: npt.ArrayLike,
        returns_to_go: npt.ArrayLike,
        timesteps: npt.ArrayLike,
    ) -> Prompt: ...
    def eval_plan(self, split: str = "test", episodes: Optional[int] = None) -> List[TaskPlan]: ...
    def set_prompt(self, prompt: Union[Prompt, Sequence[Prompt]]) -> None: ...
    def reset(self, n_episodes: int, target_return: Optional[float] = None) -> None: ...
    def restart(self, episodes: Sequence[int]) -> None: ...
    def act(self, obs: npt.ArrayLike, reward: Optional[npt.ArrayLike] = None) -> F32: ...
    def episode_returns(self) -> List[Optional[float]]: ...

def write_dataset(
    path: _Path,
    trajectories: Sequence[Dict[str, Any]],
    obs_dim: int,
    act_dim: int,
    env: Optional[str] = None,
    task: Optional[int] = None,
    mode: Optional[str] = None,
) -> None: ...
def check_dims(env: str, obs_dim: int, act_dim: int) -> None: ...
def bench_envs(
    families: Sequence[str], steps_per_env: int, vec_envs: int, threads: Sequence[int], seed: int = 0
) -> str: ...
