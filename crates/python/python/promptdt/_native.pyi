"""Typed stubs of promptdt._native (the Rust extension module)."""
from os import PathLike
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple, Union, final

import numpy as np
import numpy.typing as npt

_Path = Union[str, PathLike]
_F32 = npt.NDArray[np.float32]

# The module's own __all__ (PyO3 lists everything it adds); stubtest checks the two agree.
__all__ = [
    "__version__",
    "LIBTORCH_VERSION",
    "load_dataset",
    "write_dataset",
    "check_dims",
    "families",
    "family_info",
    "prompt_indices",
    "task_params",
    "render",
    "train",
    "evaluate",
    "collect_scripted",
    "is_scripted",
    "experiments",
    "collect_from_agent",
    "collect_policy",
    "set_num_threads",
    "bench_envs",
    "VecEnv",
    "Policy",
    "Prompt",
    "PromptBandit",
    "Adaptation",
    "TaskPlan",
]

__version__: str
LIBTORCH_VERSION: str

def load_dataset(path: _Path) -> Dict[str, Any]: ...
def families() -> Dict[str, Dict[str, Any]]: ...
def family_info(env: str) -> Dict[str, Any]: ...
def task_params(family: str, task: int) -> str: ...
def render(
    env: VecEnv, index: int, width: int = ..., height: int = ...
) -> npt.NDArray[np.uint8]: ...
def train(
    out: _Path,
    config: Optional[_Path] = None,
    resume: bool = False,
    seed: Optional[int] = None,
    iterations: Optional[int] = None,
    method: Optional[str] = None,
    device: Optional[str] = None,
    matmul: Optional[str] = None,
    data: Optional[_Path] = None,
    progress: Optional[Callable[[Dict[str, Any]], Any]] = None,
    env: Optional[Callable[[Dict[str, Any]], Any]] = None,
) -> Dict[str, Any]: ...
def evaluate(
    run_dir: _Path,
    episodes: Optional[int] = None,
    split: str = "test",
    device: Optional[str] = None,
    data: Optional[_Path] = None,
    prompt_strategy: Optional[str] = None,
    prompt_episodes: Optional[int] = None,
    prompt_length: Optional[int] = None,
    adapt: Optional[str] = None,
    adapt_steps: Optional[int] = None,
    adapt_batch: Optional[int] = None,
    progress: Optional[Callable[[Dict[str, Any]], Any]] = None,
    env: Optional[Callable[[Dict[str, Any]], Any]] = None,
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
def collect_policy(
    suite: _Path,
    out: _Path,
    policy: Callable[[_F32, Dict[str, Any]], Any],
    policy_name: str,
    medium_policy: Optional[Callable[[_F32, Dict[str, Any]], Any]] = None,
    medium_name: Optional[str] = None,
    factory: Optional[Callable[[Dict[str, Any]], Any]] = None,
    seed: int = 0,
    episodes: Optional[int] = None,
    prompt_episodes: Optional[int] = None,
    modes: Optional[List[str]] = None,
    tasks: Optional[List[int]] = None,
    action_noise: Optional[float] = None,
    medium_noise: Optional[float] = None,
    envs_per_task: Optional[int] = None,
    progress: Optional[Callable[[Dict[str, Any]], Any]] = None,
) -> int: ...
def set_num_threads(threads: int) -> None: ...

# PyO3 classes are final (not subclassable) and built by `__new__`.
@final
class VecEnv:
    @property
    def family(self) -> str: ...
    @property
    def tasks(self) -> List[int]: ...
    @property
    def obs_dim(self) -> int: ...
    @property
    def act_dim(self) -> int: ...
    @property
    def horizon(self) -> int: ...
    @property
    def num_envs(self) -> int: ...
    def __new__(cls, family: str, tasks: Sequence[int], threads: Optional[int] = None) -> "VecEnv": ...
    def reset(self, seeds: Sequence[int], indices: Optional[Sequence[int]] = None) -> _F32: ...
    def step(
        self, actions: npt.ArrayLike, mask: Optional[Sequence[bool]] = None
    ) -> Tuple[_F32, _F32, npt.NDArray[np.bool_], npt.NDArray[np.bool_]]: ...
    def last_success(self) -> Optional[npt.NDArray[np.bool_]]: ...

@final
class Prompt:
    @property
    def steps(self) -> int: ...
    @property
    def states(self) -> _F32: ...
    @property
    def actions(self) -> _F32: ...
    @property
    def returns_to_go(self) -> _F32: ...
    @property
    def timesteps(self) -> npt.NDArray[np.int64]: ...
    @property
    def mask(self) -> _F32: ...
    @property
    def segments(self) -> List[Dict[str, int]]: ...

@final
class PromptBandit:
    @property
    def task(self) -> int: ...
    def choose(self) -> Prompt: ...
    def update(self, episode_return: float) -> None: ...

@final
class Adaptation:
    @property
    def kind(self) -> str: ...
    @property
    def task(self) -> int: ...
    @property
    def log(self) -> Dict[str, Any]: ...

@final
class TaskPlan:
    @property
    def name(self) -> str: ...
    @property
    def index(self) -> int: ...
    @property
    def seeds(self) -> List[int]: ...
    @property
    def prompt(self) -> Optional[Prompt]: ...

@final
class Policy:
    @property
    def obs_dim(self) -> int: ...
    @property
    def act_dim(self) -> int: ...
    @property
    def k(self) -> int: ...
    @property
    def method(self) -> str: ...
    @property
    def env(self) -> str: ...
    @property
    def uses_prompt(self) -> bool: ...
    @property
    def target_return(self) -> float: ...
    @property
    def rtg_scale(self) -> float: ...
    @property
    def max_ep_len(self) -> int: ...
    @property
    def iteration(self) -> int: ...
    @property
    def prompt_steps(self) -> int: ...
    @staticmethod
    def load(
        run_dir: _Path, device: str = "cpu", data: Optional[_Path] = None, threads: Optional[int] = None
    ) -> "Policy": ...
    def prompt_tasks(self) -> List[int]: ...
    def task_prompt(
        self,
        task: int,
        seed: Optional[int] = None,
        prompt_strategy: Optional[str] = None,
        observation: Optional[npt.ArrayLike] = None,
        prompt_episodes: Optional[int] = None,
        prompt_length: Optional[int] = None,
    ) -> Prompt: ...
    def prompt(
        self,
        states: npt.ArrayLike,
        actions: npt.ArrayLike,
        returns_to_go: npt.ArrayLike,
        timesteps: npt.ArrayLike,
    ) -> Prompt: ...
    def prompt_bandit(
        self,
        task: int,
        seed: Optional[int] = None,
        rule: Optional[str] = None,
        epsilon: Optional[float] = None,
        prompt_episodes: Optional[int] = None,
        prompt_length: Optional[int] = None,
        stride: Optional[int] = None,
    ) -> PromptBandit: ...
    def adapt(
        self,
        task: int,
        adapt: str,
        seed: Optional[int] = None,
        prompt_strategy: Optional[str] = None,
        steps: Optional[int] = None,
        batch: Optional[int] = None,
        lr: Optional[float] = None,
    ) -> Adaptation: ...
    def eval_plan(self, split: str = "test", episodes: Optional[int] = None) -> List[TaskPlan]: ...
    def set_prompt(self, prompt: Union[Prompt, Sequence[Prompt], Adaptation]) -> None: ...
    def reset(self, n_episodes: int, target_return: Optional[float] = None) -> None: ...
    def restart(self, episodes: Sequence[int]) -> None: ...
    def act(
        self,
        obs: npt.ArrayLike,
        reward: Optional[npt.ArrayLike] = None,
        done: Optional[npt.ArrayLike] = None,
    ) -> _F32: ...
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
def prompt_indices(returns: Sequence[float], rule: str) -> List[int]: ...
def bench_envs(
    families: Sequence[str], steps_per_env: int, vec_envs: int, threads: Sequence[int], seed: int = 0
) -> str: ...
