"""The servo's current torque as a fifth torque-model input (issue 30, item 2): the feature,
training, the model folder and evaluation carry it; a folder without it is unchanged."""

from __future__ import annotations

import numpy as np
import pytest
from support.synthetic import feature_config, synthetic_samples

from jaxinertia.app.pipeline import evaluate_models, train
from jaxinertia.checkpoints import load_models
from jaxinertia.errors import UsageError
from jaxinertia.evaluation import random_sets
from jaxinertia.features import FeatureConfig, featurize
from jaxinertia.samples import save_native
from jaxinertia.training import TrainConfig, feature_config_from


def test_the_current_is_a_fifth_input_scaled_like_the_torque():
    d = synthetic_samples(np.random.default_rng(0), n=50)
    plain = feature_config_from(d)
    with_current = feature_config_from(d, current_input=True)
    assert plain.current_scale is None and plain.n_inputs == 4
    np.testing.assert_array_equal(with_current.current_scale, with_current.tau_scale)
    f4 = np.asarray(featurize(plain, d.q, d.q_d, d.direction, d.current_tau))
    f5 = np.asarray(featurize(with_current, d.q, d.q_d, d.direction, d.current_tau))
    assert f4.shape == (50, 4, 4) and f5.shape == (50, 4, 5)
    np.testing.assert_array_equal(f5[..., :4], f4)
    np.testing.assert_allclose(f5[..., 4], d.current_tau / with_current.tau_scale, rtol=1e-12)
    # The four-input configuration ignores a current; the five-input one needs it.
    np.testing.assert_array_equal(np.asarray(featurize(plain, d.q, d.q_d, d.direction)), f4)
    with pytest.raises(ValueError, match="current"):
        featurize(with_current, d.q, d.q_d, d.direction)
    # Round trip through the folder's JSON form; the paper's form has no current key.
    assert FeatureConfig.from_dict(with_current.to_dict()).current_scale.tolist() == \
        with_current.current_scale.tolist()
    assert "current_scale" not in feature_config().to_dict()
    # A servo without a current sensor (an XL430's NaN current) cannot give the input.
    cur = np.array(d.current_tau)
    cur[:, 1] = np.nan
    with pytest.raises(UsageError, match=r"joints \[2\] have none"):
        feature_config_from(d.replace(current_tau=cur), current_input=True)


def test_models_with_the_current_input_train_save_and_read_the_current(tmp_path):
    d = synthetic_samples(np.random.default_rng(1), n=600, n_obj=2)
    f = tmp_path / "train.npz"
    save_native(f, d, {"robot": "open_manipulator_x"})
    cfg = TrainConfig(n_models=1, torque_epochs=3, attention_epochs=1, attention_sets=8,
                      attention_val_sets=4, set_size=16, current_input=True)
    info = train([f], tmp_path / "m", cfg, progress=False)
    assert info["training"]["current_input"] is True
    folder = load_models(tmp_path / "m")
    assert folder.features.n_inputs == 5
    assert folder.config["training"]["current_input"] is True
    kernel = folder.pair.torque_vars["params"]["joint0"]["hidden"]["kernel"]
    assert kernel.shape[-2] == 5  # the first layer takes five inputs per joint
    # Evaluation reads the samples' current: another current, other torques and estimates.
    sets = [random_sets(300, n_sets=4, set_size=16, seed=0)]
    obj = d.object(0)
    a, b = (evaluate_models(tmp_path / "m", [o], sets, l_max=[0.1], session_strength=0.0)
            for o in (obj, obj.replace(current_tau=obj.current_tau * 1.5)))
    assert a["objects"]["o0"]["T"]["mass_MAE_g"] != b["objects"]["o0"]["T"]["mass_MAE_g"]

