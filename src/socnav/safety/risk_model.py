"""A learned collision-risk trigger: a deep ensemble of small networks that predict, from one step's observation,
the policy's action and (as inputs it may ignore) the uncertainty estimates, a collision within the next H steps.

The paper's idea -- an unfamiliar situation makes the layer more cautious -- applied where it can work: the
ensemble's spread is the risk model's OWN epistemic uncertainty, and the trigger fires on an upper quantile of the
risk, ``mean_m p_m + kappa * std_m p_m`` over the members (Lakshminarayanan et al. 2017), so members that disagree
raise the score. Trained on calibration episodes only (:func:`train_risk_model`, torch); scored in numpy
(:func:`risk_scores`), so the torch-free runtime decides exactly as the training code does.

The model file is a NumPy ``.npz`` read without pickle: per member and layer ``w{m}_{l}``/``b{m}_{l}``, the
features' ``mean``/``scale``, and a JSON ``meta`` (format, feature names, horizon); shapes and finiteness are
checked on load (:func:`load_risk_model`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from pydantic import Field

from socnav.config import StrictModel
from socnav.io import UntrustedInputError, atomic_path
from socnav.safety.triggers import (
    ScoreTrigger,
    TriggerError,
    TriggerInputs,
    TriggerSpec,
    intended_relative_motion,
    predicted_clearance,
    register_trigger,
    time_to_contact,
)

__all__ = [
    "GEOMETRY_FEATURES",
    "RISK_MODEL_FORMAT",
    "UNCERTAINTY_FEATURES",
    "RiskModel",
    "RiskModelTrigger",
    "embed_risk_model",
    "load_risk_model",
    "read_risk_model_bytes",
    "risk_features",
    "risk_model_from_bytes",
    "risk_scores",
    "save_risk_model",
    "train_risk_model",
]

RISK_MODEL_FORMAT = 1
#: The geometric features of one step (robot frame of the observation; clipped so that ``inf`` never enters).
GEOMETRY_FEATURES = ("gap", "closing_speed", "relative_speed", "gap_change", "time_to_contact", "clearance_1s",
                     "clearance_3s", "bearing_cos", "bearing_sin", "crowd_1m", "crowd_2m", "speed",
                     "goal_heading_cos", "goal_heading_sin", "action_speed", "action_heading")
#: The uncertainty estimates a model may also read (windowed, as the rule reads them; log1p-scaled).
UNCERTAINTY_FEATURES = ("u_ep_speed", "u_ep_heading", "u_al_speed", "u_al_heading", "u_feat")
MAX_MODEL_BYTES = 16 * 1024 * 1024
MAX_MEMBERS, MAX_WIDTH, MAX_LAYERS = 32, 1024, 8
FAR, LONG = 5.0, 5.0  # metres and seconds: beyond these every gap and time looks the same to the model


def risk_features(inputs: TriggerInputs, uncertainty: bool) -> np.ndarray:
    """(B, F) features of one step (:data:`GEOMETRY_FEATURES`, then :data:`UNCERTAINTY_FEATURES` if
    ``uncertainty``)."""
    nearest = inputs.nearest
    present = nearest.present
    gap = np.where(present, np.clip(nearest.gap, -1.0, FAR), FAR)
    previous = np.where(np.isfinite(inputs.previous_gap), np.clip(inputs.previous_gap, -1.0, FAR), gap)
    positions, velocities, radii, mask = intended_relative_motion(inputs)
    ttc = np.where(mask, time_to_contact(positions, velocities, radii), np.inf)
    soonest = ttc.min(axis=1) if ttc.shape[1] else np.full(len(gap), np.inf)
    humans = np.asarray(inputs.observation["humans"], dtype=np.float64)
    gaps = np.where(mask, humans[:, :, 6], np.inf)
    nearest_row = np.maximum(mask.sum(axis=1) - 1, 0)  # rows are sorted farthest first: the nearest is last
    rel = humans[np.arange(len(gap)), nearest_row, :2]
    angle = np.arctan2(rel[:, 1], rel[:, 0]) - np.asarray(inputs.observation["robot"], dtype=np.float64)[:, 1]
    robot = np.asarray(inputs.observation["robot"], dtype=np.float64)
    actions = np.clip(np.asarray(inputs.actions, dtype=np.float64), -1, 1)
    columns = [gap, np.where(present, nearest.closing_speed, 0.0), np.where(present, nearest.relative_speed, 0.0),
               gap - previous, np.minimum(soonest, LONG),
               np.clip(predicted_clearance(inputs, 1.0), -1.0, FAR),
               np.clip(predicted_clearance(inputs, 3.0), -1.0, FAR),
               np.where(present, np.cos(angle), 0.0), np.where(present, np.sin(angle), 0.0),
               (gaps < 1.0).sum(axis=1).astype(np.float64), (gaps < 2.0).sum(axis=1).astype(np.float64),
               robot[:, 2], np.cos(robot[:, 1]), np.sin(robot[:, 1]), actions[:, 0], actions[:, 1]]
    if uncertainty:
        columns += [np.log1p(np.maximum(np.asarray(inputs.uncertainty[key], dtype=np.float64), 0.0))
                    for key in UNCERTAINTY_FEATURES]
    return np.column_stack(columns)


@dataclass(frozen=True)
class RiskModel:
    """A trained ensemble: ``layers[m]`` the (weight (in, out), bias (out,)) pairs of member m (ReLU between
    layers, a logit out), the features' ``mean`` and ``scale``, and what it reads."""

    layers: tuple[tuple[tuple[np.ndarray, np.ndarray], ...], ...]
    mean: np.ndarray
    scale: np.ndarray
    uncertainty: bool
    horizon_steps: int

    @property
    def feature_names(self) -> tuple[str, ...]:
        return GEOMETRY_FEATURES + (UNCERTAINTY_FEATURES if self.uncertainty else ())

    def member_probabilities(self, features: np.ndarray) -> np.ndarray:
        """(M, B) each member's collision probability."""
        x0 = (np.asarray(features, dtype=np.float64) - self.mean) / self.scale
        out = []
        for member in self.layers:
            x = x0
            for index, (weight, bias) in enumerate(member):
                x = x @ weight + bias
                if index < len(member) - 1:
                    x = np.maximum(x, 0.0)
            out.append(1.0 / (1.0 + np.exp(-np.clip(x[:, 0], -60, 60))))
        return np.stack(out)


def risk_scores(model: RiskModel, features: np.ndarray, kappa: float) -> np.ndarray:
    """(B,) the upper risk ``mean_m p_m + kappa * std_m p_m`` over the members."""
    probabilities = model.member_probabilities(features)
    return probabilities.mean(axis=0) + kappa * probabilities.std(axis=0)


def save_risk_model(model: RiskModel, path: str | Path) -> Path:
    """Write ``model`` atomically as ``.npz`` (no pickle)."""
    arrays: dict[str, Any] = {"mean": model.mean, "scale": model.scale}
    for m, member in enumerate(model.layers):
        for index, (weight, bias) in enumerate(member):
            arrays[f"w{m}_{index}"], arrays[f"b{m}_{index}"] = weight, bias
    meta = {"format": RISK_MODEL_FORMAT, "features": list(model.feature_names), "uncertainty": model.uncertainty,
            "horizon_steps": model.horizon_steps, "members": len(model.layers), "layers": len(model.layers[0])}
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    path = Path(path)
    with atomic_path(path) as temporary, open(temporary, "wb") as stream:
        np.savez(stream, **arrays)
    return path


def load_risk_model(path: str | Path) -> RiskModel:
    """Read and check a risk-model file: no pickle, at most 16 MiB, the format known, every array present,
    finite and of matching shape. :class:`TriggerError` (one line naming the file and what is wrong) otherwise."""

    return risk_model_from_bytes(read_risk_model_bytes(path), f"risk-model file {path}")


def read_risk_model_bytes(path: str | Path) -> bytes:
    """The bytes of a risk-model file, at most 16 MiB (:class:`TriggerError` naming the file otherwise)."""
    from socnav.io import read_bounded

    path = Path(path)
    try:
        return read_bounded(path, MAX_MODEL_BYTES)
    except (OSError, UntrustedInputError) as exc:
        raise TriggerError(f"risk-model file {path}: {getattr(exc, 'strerror', None) or exc}") from None


def risk_model_from_bytes(raw: bytes, what: str = "risk model") -> RiskModel:
    """A risk model from the bytes of its ``.npz`` (no pickle; shapes, finiteness and format checked);
    :class:`TriggerError` naming ``what`` otherwise."""
    import io
    import zipfile

    try:
        with np.load(io.BytesIO(raw), allow_pickle=False) as data:
            arrays = {key: data[key] for key in data.files}
    except (ValueError, OSError, zipfile.BadZipFile, EOFError) as exc:
        raise TriggerError(f"{what} is not a risk model (.npz without pickle): {exc}") from None
    try:
        return _checked_model(arrays)
    except (KeyError, ValueError, TypeError) as exc:
        raise TriggerError(f"{what} is invalid: {exc}") from None


#: Risk models that came embedded in a navigator file, by their key (``embedded:<sha256 of the .npz>``).
EMBEDDED_MODELS: dict[str, RiskModel] = {}
EMBEDDED_PREFIX = "embedded:"


def embed_risk_model(raw: bytes) -> str:
    """Check the ``.npz`` bytes of a risk model carried inside another file (a navigator) and make them loadable
    under the returned key, to use as a `TriggerSpec.model`."""
    import hashlib

    key = EMBEDDED_PREFIX + hashlib.sha256(raw).hexdigest()
    if key not in EMBEDDED_MODELS:
        EMBEDDED_MODELS[key] = risk_model_from_bytes(raw, "the embedded risk model")
    return key


def _checked_model(arrays: dict[str, np.ndarray]) -> RiskModel:
    meta = json.loads(bytes(arrays["meta"].astype(np.uint8)).decode())
    if meta.get("format") != RISK_MODEL_FORMAT:
        raise ValueError(f"format {meta.get('format')!r}, this socnav reads format {RISK_MODEL_FORMAT}")
    members, depth = int(meta["members"]), int(meta["layers"])
    if not (1 <= members <= MAX_MEMBERS and 1 <= depth <= MAX_LAYERS):
        raise ValueError(f"{members} members of {depth} layers; allowed 1...{MAX_MEMBERS} of 1...{MAX_LAYERS}")
    uncertainty = bool(meta["uncertainty"])
    names = GEOMETRY_FEATURES + (UNCERTAINTY_FEATURES if uncertainty else ())
    if tuple(meta["features"]) != names:
        raise ValueError(f"features {meta['features']} differ from this socnav's {list(names)}")
    mean, scale = arrays["mean"].astype(np.float64), arrays["scale"].astype(np.float64)
    if mean.shape != (len(names),) or scale.shape != (len(names),) or not (scale > 0).all():
        raise ValueError(f"mean/scale must be ({len(names)},) with scale > 0")
    layers = []
    for m in range(members):
        member, width = [], len(names)
        for index in range(depth):
            weight = arrays[f"w{m}_{index}"].astype(np.float64)
            bias = arrays[f"b{m}_{index}"].astype(np.float64)
            out = 1 if index == depth - 1 else weight.shape[-1]
            if weight.shape != (width, out) or bias.shape != (out,) or out > MAX_WIDTH:
                raise ValueError(f"member {m} layer {index}: weight {weight.shape}, bias {bias.shape}; expected "
                                 f"({width}, {out}) and ({out},), width <= {MAX_WIDTH}")
            member.append((weight, bias))
            width = out
        layers.append(tuple(member))
    for name, value in [("mean", mean), ("scale", scale)] + [(f"member {m}", w) for m, mem in enumerate(layers)
                                                             for pair in mem for w in pair]:
        if not np.isfinite(value).all():
            raise ValueError(f"{name} holds non-finite values")
    steps = int(meta["horizon_steps"])
    if not 1 <= steps <= 1000:
        raise ValueError(f"horizon_steps {steps}; allowed 1...1000")
    return RiskModel(tuple(layers), mean, scale, uncertainty, steps)


def train_risk_model(features: np.ndarray, labels: np.ndarray, episodes: np.ndarray, uncertainty: bool,
                     horizon_steps: int, members: int = 5, hidden: int = 64, epochs: int = 30,
                     seed: int = 0) -> RiskModel:
    """Train the ensemble (torch, CPU): each member on a bootstrap of the EPISODES (steps of one episode are not
    independent), with its own initialisation, binary cross-entropy weighted so both classes count equally.

    :param features: (N, F) :func:`risk_features` rows; ``labels`` (N,) 1 where a collision follows within
        ``horizon_steps`` steps; ``episodes`` (N,) episode ids (the bootstrap's units).
    """
    import torch

    features = np.asarray(features, dtype=np.float64)
    labels = np.asarray(labels, dtype=np.float64)
    if len(features) == 0 or labels.sum() == 0:
        raise ValueError("the risk model needs calibration steps with collisions to learn from; play more episodes")
    mean = features.mean(axis=0)
    scale = np.where(features.std(axis=0) > 1e-9, features.std(axis=0), 1.0)
    x_all = (features - mean) / scale
    generator = np.random.default_rng(seed)
    unique = np.unique(episodes)
    by_episode = {e: np.flatnonzero(episodes == e) for e in unique}
    torch.manual_seed(seed)
    layers = []
    for _ in range(members):
        drawn = generator.choice(unique, size=len(unique), replace=True)
        index = np.concatenate([by_episode[e] for e in drawn])
        x = torch.as_tensor(x_all[index], dtype=torch.float32)
        y = torch.as_tensor(labels[index], dtype=torch.float32)
        positive = float(y.sum())
        weight = (len(y) - positive) / max(positive, 1.0)
        network = torch.nn.Sequential(torch.nn.Linear(x.shape[1], hidden), torch.nn.ReLU(),
                                      torch.nn.Linear(hidden, hidden), torch.nn.ReLU(), torch.nn.Linear(hidden, 1))
        optimiser = torch.optim.Adam(network.parameters(), lr=1e-3, weight_decay=1e-4)
        loss_fn = torch.nn.BCEWithLogitsLoss(pos_weight=torch.tensor(weight))
        batch = 512
        for _epoch in range(epochs):
            order = torch.randperm(len(y))
            for start in range(0, len(y), batch):
                chosen = order[start:start + batch]
                optimiser.zero_grad()
                loss = loss_fn(network(x[chosen])[:, 0], y[chosen])
                loss.backward()
                optimiser.step()
        linear = [module for module in network if isinstance(module, torch.nn.Linear)]
        layers.append(tuple((module.weight.detach().double().numpy().T.copy(),
                             module.bias.detach().double().numpy().copy()) for module in linear))
    return RiskModel(tuple(layers), mean, scale, uncertainty, int(horizon_steps))


class _RiskParams(StrictModel):
    kappa: float = Field(1.0, ge=0, le=10, description="weight of the members' spread in the upper risk")


@register_trigger
class RiskModelTrigger(ScoreTrigger):
    """The learned collision risk (module docstring); the spec's ``model`` names the ``.npz`` file. Fires where the
    upper risk exceeds the threshold (a probability)."""

    name = "risk-model"
    Params = _RiskParams
    description = "deep ensemble predicting a collision within H steps; fires on its upper risk"
    _cache: ClassVar[dict[str, RiskModel]] = {}

    def __init__(self, spec: TriggerSpec, base: Path | None = None) -> None:
        super().__init__(spec, base)
        self.model = self.load(spec)
        self.reads_uncertainty = self.model.uncertainty

    @classmethod
    def load(cls, spec: TriggerSpec) -> RiskModel:
        if spec.model is None:
            raise TriggerError("trigger 'risk-model' needs its model file: give `model: <file>.npz`")
        if spec.model.startswith(EMBEDDED_PREFIX):
            if spec.model not in EMBEDDED_MODELS:
                raise TriggerError(f"no embedded risk model {spec.model!r} is loaded")
            return EMBEDDED_MODELS[spec.model]
        path = Path(spec.model)
        try:
            status = path.stat()
        except OSError as exc:
            raise TriggerError(f"risk-model file {path}: {exc.strerror or exc}") from None
        key = f"{path.resolve()}:{status.st_mtime_ns}:{status.st_size}"  # a retrained file is read again
        if key not in cls._cache:
            cls._cache[key] = load_risk_model(spec.model)
        return cls._cache[key]

    @classmethod
    def spec_reads_uncertainty(cls, spec: TriggerSpec) -> bool:
        return cls.load(spec).uncertainty

    def score(self, inputs: TriggerInputs) -> np.ndarray:
        features = risk_features(inputs, self.model.uncertainty)
        return risk_scores(self.model, features, self.params.kappa)

