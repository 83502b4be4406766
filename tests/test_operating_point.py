"""runtime/operating_point.py: one owner for which beta and which item rule decide, and where each
comes from (the config's number, the file it names, the default file, the bundle)."""

from __future__ import annotations

import json
from types import SimpleNamespace

import pytest

from vs2t_edge.runtime import operating_point as op
from vs2t_edge.runtime.config import load_config

CFG = ("bundle: bundle\ndevices: {camera: {kind: replay, path: x}, arm: {kind: fake}, gate: {kind: fake}}\n"
       "scene: {fabrics: [{name: denim, kind: touched, bin: 1}]}\njournal: j.jsonl\n")


def _cfg(tmp_path, extra=""):
    (tmp_path / "c.yaml").write_text(CFG + extra)
    return load_config(tmp_path / "c.yaml")


def _override(path, beta):
    op.write_beta_override(path, {"beta": beta, "objective": "test"}, bundle_beta=0.5, source="test")


def test_beta_precedence_number_then_named_file_then_default_file_then_bundle(tmp_path):
    assert op.resolve_beta(_cfg(tmp_path)) == (None, "bundle manifest")
    default = op.override_path_for(tmp_path / "bundle")
    assert default == tmp_path / "bundle.beta_override.json"
    _override(default, 2.0)
    assert op.resolve_beta(_cfg(tmp_path)) == (2.0, str(default))
    named = tmp_path / "elsewhere.json"
    _override(named, 3.0)
    assert op.resolve_beta(_cfg(tmp_path, f"beta_override_file: {named}\n")) == (3.0, str(named))
    beta, source = op.resolve_beta(_cfg(tmp_path, f"beta_override_file: {named}\nbeta_override: 4.0\n"))
    assert beta == 4.0 and "beta_override" in source
    # calibrate-threshold writes where the daemon reads, and refuses when a number would shadow it
    assert op.override_file_for(_cfg(tmp_path)) == (default, "")
    path, problem = op.override_file_for(_cfg(tmp_path, "beta_override: 4.0\n"))
    assert path is None and "would be ignored" in problem


def test_the_override_keeps_its_history_and_a_bad_file_is_named(tmp_path):
    path = tmp_path / "b.beta_override.json"
    _override(path, 1.0)
    _override(path, 2.0)
    data = json.loads(path.read_text())
    assert data["beta"] == 2.0 and data["history"][0]["beta"] == 1.0
    assert json.loads(path.with_name(path.name + ".prev").read_text())["beta"] == 1.0
    path.write_text('{"beta": NaN}')
    with pytest.raises(op.OverrideFileError, match="b.beta_override.json: beta nan is not finite"):
        op.read_beta_override(path)


def test_the_scene_models_item_rule_unless_the_config_writes_a_confidence(tmp_path):
    scene = SimpleNamespace(confidence=0.97, untouched_confidence=0.9, evidence_weight=0.25, open_threshold=40.0,
                            known_margin=0.0, untouched=frozenset({"wool"}))
    model = SimpleNamespace(scene_model=scene)
    confidence, opts = op.evidence_settings(_cfg(tmp_path), model)
    assert confidence == 0.97 and opts == {"weight": 0.25, "open_threshold": 40.0, "known_margin": 0.0,
                                           "class_confidence": {"wool": 0.9}}
    confidence, opts = op.evidence_settings(_cfg(tmp_path, "evidence: {confidence: 0.8}\n"), model)
    assert confidence == 0.8 and opts["weight"] == 0.25 and opts["class_confidence"] == {"wool": 0.9}
    plain = SimpleNamespace(scene_model=None)
    cfg = _cfg(tmp_path)
    assert op.evidence_settings(cfg, plain) == (cfg.confidence, {})


def test_the_cell_and_the_simulated_jobs_build_the_scene_models_item_rule_alike(tmp_path):
    """The cell's evidence (runtime/wiring.py) and the simulated jobs of training's report and the
    bench (runtime/sorting.py) both take the scene model's rule from operating_point: one item rule."""
    from vs2t_edge.runtime.sorting import Scene, scene_evidence
    from vs2t_edge.runtime.wiring import evidence_factory_for

    scene = SimpleNamespace(confidence=0.97, untouched_confidence=0.9, evidence_weight=0.25, open_threshold=40.0,
                            known_margin=1.5, untouched=frozenset({"wool"}))
    (tmp_path / "c.yaml").write_text(CFG.replace("{name: denim, kind: touched, bin: 1}",
                                                 "{name: denim, kind: touched, bin: 1}, {name: wool, kind: untouched, "
                                                 "bin: 2}"))
    cfg = load_config(tmp_path / "c.yaml")
    cell = evidence_factory_for(cfg, SimpleNamespace(scene_model=scene))()
    jobs = scene_evidence(scene, cfg.max_presses)(Scene(("denim",), ("wool",), ()))
    for ev in (cell, jobs):
        assert (ev.confidence, ev.weight, ev.open_threshold, ev.known_margin) == (0.97, 0.25, 40.0, 1.5)
        assert dict(zip(ev.classes, ev._needed.tolist())) == {"denim": 0.97, "wool": 0.9}
