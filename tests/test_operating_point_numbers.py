"""The operating point's refusal rules take only numbers that mean something (runtime/scene_model.py,
runtime/evidence.py, runtime/operating_point.py): ``open_threshold`` and ``known_margin`` are a
number of at least 0, or +inf for the rule off (training's grids: quantiles of squared distances,
margins 0 / 2 / 8 / inf). -inf was taken as "off" (the rules run only on a finite value) where by
its arithmetic it would refuse every piece; a negative value refuses pieces the rule does not
describe. Either is refused naming the file and key."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from vs2t_edge.runtime import operating_point as op
from vs2t_edge.runtime.evidence import Evidence
from vs2t_edge.runtime.scene_model import SceneModel, SceneModelError

OFF = {"press_var": 1.0, "offset_var_touched": 0.1, "offset_var_untouched": 20.0, "item_temperature": 1.0,
       "item_bias": 0.0, "known_margin": math.inf, "open_threshold": math.inf, "confidence": 0.9,
       "untouched_confidence": 0.9}


def _params(**scalars):
    means = np.array([[0.0, 0, 0], [8, 0, 0], [0, 8, 0]])
    sm = SceneModel(("f00", "f02", "f03"), frozenset({"f03"}), np.zeros(6), np.eye(6)[:, :3], means,
                    known_margin=0.0, open_threshold=40.0, labels_rule=OFF)
    return {**sm.to_params(), **{k: np.float64(v) for k, v in scalars.items()}}


@pytest.mark.parametrize("key", ["known_margin", "open_threshold", "labels_known_margin", "labels_open_threshold"])
@pytest.mark.parametrize("value", [-math.inf, math.nan, -1.0])
def test_a_scene_model_refuses_a_refusal_rule_that_means_nothing(key, value):
    with pytest.raises(SceneModelError, match=rf"'{key}'"):
        SceneModel.from_params(_params(**{key: value}))


@pytest.mark.parametrize("key", ["known_margin", "open_threshold", "labels_known_margin", "labels_open_threshold"])
def test_inf_is_the_rule_off_and_zero_is_a_rule(key):
    assert getattr_rule(SceneModel.from_params(_params(**{key: math.inf})), key) == math.inf
    assert getattr_rule(SceneModel.from_params(_params(**{key: 0.0})), key) == 0.0


def getattr_rule(model, key):
    return model.labels_rule[key[len("labels_"):]] if key.startswith("labels_") else getattr(model, key)


def test_the_decision_file_is_named_with_the_key(tmp_path, capsys):
    """`validate-config --check-bundle` (and the bundle's load) names decision.npz and the key."""
    from vs2t_edge.cli import main

    (tmp_path / "bundle").mkdir()
    (tmp_path / "bundle" / "manifest.json").write_text(json.dumps({
        "format": "vs2t-bundle", "format_version": 2, "classes": {"touched": ["f00", "f02"], "untouched": ["f03"]},
        "decision": {"file": "decision.npz"}}))
    np.savez(tmp_path / "bundle" / "decision.npz", **_params(known_margin=-math.inf))
    (tmp_path / "c.yaml").write_text(
        "bundle: bundle\nthreads: 1\ndevices: {camera: {kind: replay, path: x}, arm: {kind: fake}, gate: {kind: fake}}"
        "\nscene: {fabrics: [{name: f00, kind: touched, bin: 1}, {name: f02, kind: touched, bin: 2}]}\n"
        "journal: j.jsonl\n")
    assert main(["validate-config", str(tmp_path / "c.yaml"), "--check-bundle"]) == 2
    err = capsys.readouterr().err
    assert "decision.npz" in err and "'known_margin'" in err, err


@pytest.mark.parametrize("kw", [{"known_margin": -math.inf}, {"open_threshold": -math.inf},
                                {"open_threshold": -1.0}, {"known_margin": -0.5}])
def test_the_evidence_refuses_them_too(kw):
    """-inf switched the rule off silently (it runs only on a finite value)."""
    with pytest.raises(ValueError, match=next(iter(kw))):
        Evidence(["a", "b"], 0.9, 4, **kw)


def _manifest(scene_model: bool) -> dict:
    return {"beta": 0.5, "manifest_sha256": "ab" * 32, **({"decision": {"file": "decision.npz"}} if scene_model else {})}


def test_an_override_file_that_names_no_bundle_is_refused_where_its_beta_decides(tmp_path):
    """Without 'bundle_seal' and 'bundle_beta' nothing tells whether the file's beta is in this
    bundle's router's units: a file left from another bundle would route every press by a foreign
    threshold. Where beta decides (a bundle without a scene model) it is refused naming both keys;
    with a scene model beta sorts nothing (the scene model decides), and the file is taken."""
    path = tmp_path / "bundle.beta_override.json"
    path.write_text(json.dumps({"beta": 3.0}))
    with pytest.raises(op.OverrideFileError, match=rf"{path.name}.*'bundle_seal'.*'bundle_beta'"):
        op.read_beta_override(path, _manifest(scene_model=False))
    assert op.read_beta_override(path, _manifest(scene_model=True)) == 3.0
    path.write_text(json.dumps({"beta": 3.0, "bundle_beta": 0.5}))  # a file from before the seal: judged by it
    assert op.read_beta_override(path, _manifest(scene_model=False)) == 3.0


def test_an_override_file_without_beta_names_the_key(tmp_path):
    path = tmp_path / "bundle.beta_override.json"
    path.write_text(json.dumps({"bundle_seal": "ab" * 32}))
    with pytest.raises(op.OverrideFileError, match=rf"{path.name}.*no key 'beta'"):
        op.read_beta_override(path, _manifest(scene_model=False))
    path.write_text(json.dumps({"beta": "-inf", "bundle_seal": "ab" * 32}))
    with pytest.raises(op.OverrideFileError, match=rf"{path.name}.*beta -inf is not finite"):
        op.read_beta_override(path, _manifest(scene_model=False))
