"""SafeNavigator with a score trigger decides as the torch SafePolicy with the same trigger, step for step: the
analytic time to collision, the stateful conformal shield, and a risk model that reads the uncertainty."""

from __future__ import annotations

import numpy as np
import pytest

import socnav
from socnav.runtime import DropoutStream, SafeNavigator
from socnav.safety.risk_model import GEOMETRY_FEATURES, UNCERTAINTY_FEATURES, save_risk_model, train_risk_model
from socnav.safety.triggers import TriggerSpec, load_safety, save_trigger_spec


def _risk_model_file(tmp_path):
    """A small risk model that reads the uncertainty too (trained on synthetic rows: only its use is compared)."""
    rng = np.random.default_rng(0)
    features = rng.normal(size=(300, len(GEOMETRY_FEATURES) + len(UNCERTAINTY_FEATURES)))
    features[:, 0] = rng.uniform(0, 5, 300)  # the gap
    labels = (features[:, 0] < 1.0).astype(float)
    model = train_risk_model(features, labels, np.arange(300) // 10, uncertainty=True, horizon_steps=4,
                             members=2, epochs=3)
    return save_risk_model(model, tmp_path / "risk.npz")


@pytest.mark.parametrize("embedded", [False, True], ids=["trigger-file", "exported-with-the-trigger"])
@pytest.mark.parametrize("trigger", ["time-to-collision", "conformal", "risk-model"])
def test_navigator_reproduces_safe_policy_episodes_with_a_trigger(pretrained_policy, navigator_file, tmp_path,
                                                                   trigger, embedded, tracked_state):
    """Given at load (a trigger file) or carried by the navigator file (`socnav export --thresholds TRIGGER_FILE`:
    format version 4, a risk model's weights embedded), the trigger decides as in the torch SafePolicy."""
    from socnav.envs.env import SocialNavEnv
    from socnav.safety import SafePolicy
    from socnav.uncertainty import MCDropoutEstimator

    thresholds = {"time-to-collision": -2.0, "conformal": -0.6, "risk-model": 0.5}[trigger]
    model = str(_risk_model_file(tmp_path)) if trigger == "risk-model" else None
    spec = TriggerSpec.create(trigger=trigger, threshold=thresholds, model=model, hold_steps=1)
    path = save_trigger_spec(spec, tmp_path / "trigger.yaml")  # through its file, as a user would give it
    assert load_safety(path) == spec
    config = socnav.load_config({"scenario": "circle_crossing", "n_humans": 5})
    seed = 3
    estimator = MCDropoutEstimator(pretrained_policy, k=20, uniforms=DropoutStream(seed))
    reference = SafePolicy(pretrained_policy, estimator, spec, config, n_envs=1)
    if embedded:
        exported = socnav.export_onnx(pretrained_policy, tmp_path / "navigator.onnx", thresholds=str(path), k=20)
        navigator = SafeNavigator.load(exported, seed=seed)
        assert navigator.network.record.version == 4
    else:
        navigator = SafeNavigator.load(navigator_file, thresholds=path, seed=seed)
    env = SocialNavEnv(config)
    fallbacks = steps = 0
    for episode in range(2):
        obs, _ = env.reset(seed=100 * seed + episode)
        reference.reset()
        navigator.reset()
        done = False
        while not done:
            decision = navigator.act(*tracked_state(env.world))
            expected, _ = reference.predict(obs)
            assert decision.fallback == bool(reference.last_fallback[0])
            np.testing.assert_allclose(decision.action, expected, rtol=0, atol=1e-5)
            fallbacks += decision.fallback
            steps += 1
            obs, _, terminated, truncated, _ = env.step(decision.action)
            done = terminated or truncated
    assert 0 < fallbacks < steps  # both the fallback and the policy were compared
    decision = navigator.thresholds
    assert isinstance(decision, TriggerSpec)
    assert (decision.trigger, decision.params, decision.threshold) == (spec.trigger, spec.params, spec.threshold)


def test_an_exported_trigger_is_checked_at_load(pretrained_policy, tmp_path):
    """A navigator file whose trigger record is broken is refused at load, in one line, as any bad metadata: an
    unknown trigger, a risk model that is not base64 or not a model, a risk model on another trigger."""
    import json

    import onnx

    from socnav.runtime import NavigatorLoadError
    from socnav.runtime.format import CHECKSUM_KEY, METADATA_KEY, seal

    spec = TriggerSpec.create(trigger="time-to-collision", threshold=-2.0)
    exported = socnav.export_onnx(pretrained_policy, tmp_path / "navigator.onnx",
                                  thresholds=str(save_trigger_spec(spec, tmp_path / "ttc.yaml")))
    for name, change, match in [("unknown", {"trigger": "time-to-colision"}, "did you mean 'time-to-collision'"),
                                ("not-base64", {"trigger": "risk-model", "risk_model": "%%%"}, "not base64"),
                                ("not-a-model", {"trigger": "risk-model", "risk_model": "AAAA"}, "not a risk model"),
                                ("model-on-ttc", {"risk_model": "AAAA"}, "embeds its model")]:
        model = onnx.load(str(exported))
        entries = {e.key: e for e in model.metadata_props}
        metadata = json.loads(entries[METADATA_KEY].value)
        metadata["safety"]["trigger"].update(change)
        entries[METADATA_KEY].value = json.dumps(metadata)
        entries[CHECKSUM_KEY].value = "0" * 64  # as the exporter writes it before sealing: a valid checksum again
        broken = tmp_path / f"{name}.onnx"
        broken.write_bytes(seal(model.SerializeToString()))
        with pytest.raises(NavigatorLoadError, match=match):
            SafeNavigator.load(broken)
