"""Named hyperparameter presets of the five paper variants and ``make_model`` to build an ODVPPO from one.
``ppo``, ``ppo-drop``, ``odv-ppo-noloss``, ``odv-ppo``, ``odv-ppo-drop`` (paper Table I; docs/training.md, Presets).

ODV presets follow paper Table I (lr 2.5e-4, n_steps 128 per env, batch 128, p_train 0.1, p_test 0.5,
log-sigma clamp [-20, 0.25], lambda_sigma 0.3, sigma^2_tgt 0); the PPO presets use SB3-style defaults (lr 3e-4,
n_steps 128, batch 128, 10 epochs, gamma 0.99, GAE 0.95, clip 0.2, ent 0, vf 0.5) until the project's own Optuna
search replaces them. Every field can be overridden per run (``make_model(..., overrides={...})``).
"""

from __future__ import annotations

from types import MappingProxyType
from typing import Annotated, Any, Literal

import torch as th
from pydantic import ConfigDict, Field, StrictInt, ValidationError, model_validator

from socnav.config import RENAMED_FIELDS, StrictModel, format_validation_error
from socnav.rl.odv_ppo import ODVPPO
from socnav.rl.policy import ODVActorCriticPolicy

__all__ = ["ALGOS", "PRESETS", "AlgoConfig", "AlgoName", "describe_override_error", "large_batch_overrides",
           "make_model", "policy_kwargs_for", "resolve_config"]

AlgoName = Literal["ppo", "ppo-drop", "odv-ppo-noloss", "odv-ppo", "odv-ppo-drop"]


#: Upper bounds: far beyond any PPO setting in use, below sizes whose buffers or networks cannot be allocated.
_MAX_STEPS = 1_000_000
_MAX_WIDTH = 4096
LayerSizes = tuple[Annotated[StrictInt, Field(gt=0, le=_MAX_WIDTH)], ...]


class AlgoConfig(StrictModel):
    """All hyperparameters of one training run (PPO, network, ODV, dropout, runtime); every number finite, every
    count a strict integer (socnav.config.StrictModel). Defaults are written ``Field(default=...)``: the keyword is
    what type checkers read as a default."""

    model_config = ConfigDict(frozen=True)

    # -- PPO (SB3 names) --
    learning_rate: float = Field(default=3e-4, gt=0, le=1)
    n_steps: StrictInt = Field(default=128, gt=0, le=_MAX_STEPS, description="rollout steps per environment")
    batch_size: StrictInt = Field(default=128, gt=1, le=_MAX_STEPS, description="minibatch size of one gradient step")
    n_epochs: StrictInt = Field(default=10, gt=0, le=1000)
    gamma: float = Field(default=0.99, ge=0, le=1)
    gae_lambda: float = Field(default=0.95, ge=0, le=1)
    clip_range: float = Field(default=0.2, gt=0, le=1, description="PPO clips the policy ratio to [1 - c, 1 + c]")
    clip_range_vf: float | None = Field(default=None, gt=0, le=1e6,
                                        description="value clip, in return units (None: off)")
    normalize_advantage: bool = True
    ent_coef: float = Field(default=0.0, ge=0, le=100, description="entropy bonus weight")
    vf_coef: float = Field(default=0.5, ge=0, le=100, description="value loss weight")
    max_grad_norm: float = Field(default=0.5, gt=0, le=1e6)
    target_kl: float | None = Field(default=None, gt=0, le=1e3, description="early stop of an update (None: off)")
    # -- network (paper Fig. 3) --
    lstm_hidden_size: StrictInt = Field(default=64, gt=0, le=_MAX_WIDTH)
    n_lstm_layers: StrictInt = Field(default=2, gt=0, le=16)
    net_arch_pi: LayerSizes = Field(default=(128, 128), max_length=16)
    net_arch_vf: LayerSizes = Field(default=(128, 128), max_length=16)
    ortho_init: bool = True
    log_std_init: float = Field(default=0.0, ge=-20, le=2, description="initial log sigma (sigma in e^-20 ... e^2)")
    frame: Literal["goal", "heading"] = Field(
        default="goal", description="the frame the network reads the humans and the goal in: 'goal' (the paper's, "
        "the observation as it is) or 'heading' (the robot's heading, the range scan's frame; docs/maps.md)")
    scan_encoding: Literal["range", "nearness"] = Field(
        default="range", description="what the scan encoder reads of each beam: 'range' (range / max range) or "
        "'nearness' (exp(-range / 1 m): resolution near the robot, a dropped beam reads 'nothing near'; "
        "docs/maps.md)")
    # -- observation-dependent variance (paper IV-A) --
    odv: bool = False
    log_std_min: float = Field(default=-20.0, ge=-50, le=5)
    log_std_max: float = Field(default=0.25, ge=-50, le=5)
    variance_coef: float = Field(default=0.0, ge=0, le=1e3, description="lambda_sigma of eq. (4)")
    variance_target: float = Field(default=0.0, ge=0, le=1e3, description="sigma^2_tgt of eq. (4)")
    # -- dropout (paper IV-B) --
    p_train: float = Field(default=0.0, ge=0, lt=1, description="dropout probability during training")
    p_test: float = Field(default=0.5, ge=0, lt=1, description="MC-dropout probability at test time (stored)")
    # -- smooth driving (socnav.rl.smoothing): training-time costs, 0 = the paper's training --
    turn_penalty: float = Field(default=0.0, ge=0, le=100, description="per-step cost of |heading action| (in [-1, 1]) "
                                "subtracted from the reward the agent learns from")
    action_change_penalty: float = Field(default=0.0, ge=0, le=100, description="per-step cost of the change of the "
                                         "action from the last step (sum over speed and heading of |change| / 2)")
    # -- runtime --
    device: str = "cpu"
    torch_threads: StrictInt | None = Field(
        default=1,
        gt=0,
        le=1024,
        description=(
            "torch.set_num_threads(...) when the model is built (process-wide; None leaves torch alone). "
            "1 by default: the matrices are small, so a second intra-op thread gains only ~10-30% wall time "
            "for a single run on an idle 2-core CPU, at half the throughput per CPU-second, and OpenMP threads "
            "collapse (up to 10x slower) when the cores are shared with the env, other seeds or other jobs. "
            "Parallel seeds, one single-threaded process each, give the best total throughput."
        ),
    )

    @model_validator(mode="after")
    def _check_clamp(self) -> AlgoConfig:
        if not self.log_std_min < self.log_std_max:
            raise ValueError(f"log_std_min ({self.log_std_min}) must be < log_std_max ({self.log_std_max})")
        return self


_PPO = AlgoConfig()
_ODV = AlgoConfig(learning_rate=2.5e-4, odv=True, variance_coef=0.3)

#: name -> preset (read-only mapping).
PRESETS: MappingProxyType[str, AlgoConfig] = MappingProxyType(
    {
        "ppo": _PPO,
        "ppo-drop": _PPO.model_copy(update=dict(p_train=0.1)),
        "odv-ppo-noloss": _ODV.model_copy(update=dict(variance_coef=0.0)),
        "odv-ppo": _ODV,
        "odv-ppo-drop": _ODV.model_copy(update=dict(p_train=0.1)),
    }
)
ALGOS: tuple[str, ...] = tuple(PRESETS)


def large_batch_overrides(algo: str, batch_size: int = 512) -> dict[str, Any]:
    """Overrides that trade the preset's 128-sample minibatch for ``batch_size`` (a documented speed option).

    Fewer, larger gradient steps per rollout make training markedly faster on a CPU, because at 128 samples a
    gradient step of this small LSTM/MLP is dominated by per-call overhead rather than arithmetic (measured on a
    2-vCPU VM, odv-ppo-drop, 16 envs x 128 steps, one human: ~1,400-1,750 env-steps/s at 128 vs ~2,600 at
    512), at the price of departing from the paper's Table I. The learning rate follows the square-root
    scaling rule for Adam, ``lr * sqrt(batch_size / preset_batch_size)``.
    Use as ``make_model(algo, env, seed, overrides=large_batch_overrides(algo))``.
    """
    base = resolve_config(algo)
    return {"batch_size": batch_size, "learning_rate": base.learning_rate * (batch_size / base.batch_size) ** 0.5}


def resolve_config(algo: str, overrides: dict[str, Any] | None = None) -> AlgoConfig:
    """The preset ``algo`` with ``overrides`` applied and validated.

    :raises ValueError: unknown algo name or override key (the message lists the allowed values, or the new name
        of a renamed key), or an invalid value (pydantic's ValidationError; `describe_override_error` words it).
    """
    if algo not in PRESETS:
        raise ValueError(f"unknown algo {algo!r}; allowed values: {', '.join(ALGOS)}")
    overrides = dict(overrides or {})
    allowed = list(AlgoConfig.model_fields)
    bad = [key for key in overrides if key not in AlgoConfig.model_fields]
    old = next((key for key in bad if key in RENAMED_FIELDS), None)
    if old is not None:
        new = RENAMED_FIELDS[old]
        raise ValueError(f"unknown override key {old!r} for algo {algo!r}: it was renamed {new} (the paper's name); "
                         f"write {new} instead")
    if bad:
        raise ValueError(
            f"unknown override key{'s' if len(bad) > 1 else ''} {', '.join(map(repr, bad))} for algo {algo!r}; "
            f"allowed keys: {', '.join(allowed)}"
        )
    return AlgoConfig.model_validate({**PRESETS[algo].model_dump(), **overrides})


def describe_override_error(algo: str, error: ValueError) -> str:
    """A `resolve_config` error for a person: pydantic's through socnav's one formatter (field, bad value, allowed
    values; `resolve_config` itself keeps raising pydantic's ValidationError), socnav's own as they are."""
    if isinstance(error, ValidationError):
        return format_validation_error(error, f"invalid hyperparameters for algo {algo!r}:", AlgoConfig)
    return str(error)


def policy_kwargs_for(cfg: AlgoConfig) -> dict[str, Any]:
    """The ``ODVActorCriticPolicy`` constructor arguments of a resolved config (also used to rebuild saved policies)."""
    return dict(
        net_arch=dict(pi=list(cfg.net_arch_pi), vf=list(cfg.net_arch_vf)),
        ortho_init=cfg.ortho_init,
        log_std_init=cfg.log_std_init,
        odv=cfg.odv,
        dropout_p=cfg.p_train,
        p_test=cfg.p_test,
        log_std_min=cfg.log_std_min,
        log_std_max=cfg.log_std_max,
        lstm_hidden_size=cfg.lstm_hidden_size,
        n_lstm_layers=cfg.n_lstm_layers,
        features_extractor_kwargs={"frame": cfg.frame, "scan_encoding": cfg.scan_encoding},
    )


def _scan_setting(env: Any) -> Any:
    """The `scan` setting of the socnav world under `env` (through SB3 VecEnv and Gymnasium wrappers), or None."""
    while hasattr(env, "venv"):
        env = env.venv
    env = getattr(env, "unwrapped", env)
    config = getattr(env, "config", None)
    return getattr(config, "scan", None)


def make_model(
    algo: str,
    env: Any,
    seed: int,
    overrides: dict[str, Any] | None = None,
    tensorboard_log: str | None = None,
    verbose: int = 0,
    algo_config: AlgoConfig | None = None,
) -> ODVPPO:
    """Build an :class:`ODVPPO` for preset ``algo`` on ``env`` (an SB3 VecEnv or Gymnasium env).

    The resolved config is stored on the model (``model.algo_name``, ``model.algo_config`` as a dict) and
    therefore saved with it.

    :param algo: one of :data:`ALGOS`.
    :param env: training environment with the socnav ``Dict`` observation space.
    :param seed: seed of SB3 / torch / the env.
    :param overrides: ``{field: value}`` replacing preset values (fields of :class:`AlgoConfig`).
    :param tensorboard_log: TensorBoard log directory (None: no TensorBoard).
    :param verbose: SB3 verbosity.
    :param algo_config: the config `resolve_config(algo, overrides)` already returned (a caller that validated
        it up front passes it down instead of `overrides`, so it is not resolved twice).
    """
    if algo_config is not None and overrides:
        raise ValueError("make_model takes overrides or an already resolved algo_config, not both")
    cfg = algo_config if algo_config is not None else resolve_config(algo, overrides)
    if cfg.torch_threads is not None:
        th.set_num_threads(cfg.torch_threads)
    policy_kwargs = policy_kwargs_for(cfg)
    scan = _scan_setting(env)
    if scan is not None:  # the scan encoder pads circularly only for a full turn: it must know the field of view
        policy_kwargs = {**policy_kwargs, "features_extractor_kwargs": {
            **policy_kwargs.get("features_extractor_kwargs", {}), "scan_fov": float(scan.fov)}}
    model = ODVPPO(
        ODVActorCriticPolicy,
        env,
        variance_coef=cfg.variance_coef,
        variance_target=cfg.variance_target,
        learning_rate=cfg.learning_rate,
        n_steps=cfg.n_steps,
        batch_size=cfg.batch_size,
        n_epochs=cfg.n_epochs,
        gamma=cfg.gamma,
        gae_lambda=cfg.gae_lambda,
        clip_range=cfg.clip_range,
        clip_range_vf=cfg.clip_range_vf,
        normalize_advantage=cfg.normalize_advantage,
        ent_coef=cfg.ent_coef,
        vf_coef=cfg.vf_coef,
        max_grad_norm=cfg.max_grad_norm,
        target_kl=cfg.target_kl,
        policy_kwargs=policy_kwargs,
        tensorboard_log=tensorboard_log,
        verbose=verbose,
        seed=seed,
        device=cfg.device,
    )
    # Attributes of socnav's own on the SB3 model (ODVPPO declares neither); JSON-safe, so checkpoints store them.
    model.algo_name = algo
    model.algo_config = cfg.model_dump(mode="json")
    return model
