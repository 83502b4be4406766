"""runtime/operating_point.py: one owner for which beta and which item rule decide, and where each
comes from (the config's number, the file it names, the default file, the bundle)."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
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
                            known_margin=0.0, untouched=frozenset({"wool"}), item_rule="sum", refuse_early=True,
                            outlier_ratio=math.inf, classes=("denim", "wool", "felt"), known_only=("felt",))
    model = SimpleNamespace(scene_model=scene)
    confidence, opts = op.evidence_settings(_cfg(tmp_path), model)
    # extra presses (the config's, 0 by default) only ever for a touched class a job can list
    assert confidence == 0.97 and opts == {"weight": 0.25, "open_threshold": 40.0, "known_margin": 0.0,
                                           "class_confidence": {"wool": 0.9}, "item_model": None,
                                           "refuse_early": True, "outlier_model": None,
                                           "extend_classes": ("denim",), "extra_presses": 0}
    assert op.evidence_settings(_cfg(tmp_path, "evidence: {extra_presses: 3}\n"), model)[1]["extra_presses"] == 3
    ruled = SimpleNamespace(**{**vars(scene), "outlier_ratio": 20.0})
    assert op.evidence_settings(_cfg(tmp_path), SimpleNamespace(scene_model=ruled))[1]["outlier_model"] is ruled
    offset = SimpleNamespace(**{**vars(scene), "item_rule": "offset"})
    assert op.evidence_settings(_cfg(tmp_path), SimpleNamespace(scene_model=offset))[1]["item_model"] is offset
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
                            known_margin=1.5, untouched=frozenset({"wool"}), item_rule="sum", refuse_early=True,
                            outlier_ratio=math.inf, classes=("denim", "wool"), known_only=())
    (tmp_path / "c.yaml").write_text(CFG.replace("{name: denim, kind: touched, bin: 1}",
                                                 "{name: denim, kind: touched, bin: 1}, {name: wool, kind: untouched, "
                                                 "bin: 2}"))
    cfg = load_config(tmp_path / "c.yaml")
    cell = evidence_factory_for(cfg, SimpleNamespace(scene_model=scene))()
    jobs = scene_evidence(scene, cfg.max_presses)(Scene(("denim",), ("wool",), ()))
    for ev in (cell, jobs):
        assert (ev.confidence, ev.weight, ev.open_threshold, ev.known_margin) == (0.97, 0.25, 40.0, 1.5)
        assert ev.extra_presses == 0 and ev._extend.tolist() == [True, False]
        assert dict(zip(ev.classes, ev._needed.tolist())) == {"denim": 0.97, "wool": 0.9}
        assert ev.item_model is None and ev.refuse_early and ev.outlier_model is None


# --- an override file and the bundle it was calibrated for -------------------------------------

REPLAY_BUNDLE = __import__("pathlib").Path(__file__).parent / "replays" / "bundle"


def _deploy(tmp_path, *, beta=None, note=None):
    """The reference replays' bundle copied to tmp_path/bundle; with ``beta`` / ``note`` it is
    re-sealed as another export (what deploying a new bundle to the same folder gives)."""
    import shutil

    from vs2t_edge.runtime.bundle import seal_manifest

    dst = tmp_path / "bundle"
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(REPLAY_BUNDLE, dst)
    manifest = json.loads((dst / "manifest.json").read_text())
    if beta is not None or note is not None:
        manifest["beta"] = manifest["beta"] if beta is None else beta
        manifest["provenance"] = dict(manifest["provenance"], note=note or "another export")
        (dst / "manifest.json").write_text(json.dumps(seal_manifest(manifest), indent=2))
    return dst, manifest


BUNDLE_CFG = ("bundle: bundle\nthreads: 1\ndevices: {camera: {kind: replay, path: x}, arm: {kind: fake}, "
              "gate: {kind: fake}}\nscene: {fabrics: [{name: f00, kind: touched, bin: 1}, {name: f02, kind: touched, "
              "bin: 2}]}\njournal: j.jsonl\n")


def test_an_override_calibrated_for_another_bundle_is_refused(tmp_path):
    """beta is in the units of the router it was calibrated on (a Gaussian's novelty spans 1e7 ..
    1e12): the override beside the bundle folder, kept when a new bundle is deployed to that folder,
    routed the new bundle's presses to CLS_t / CLS_u by the old router's threshold - untouched
    pieces sorted as touched fabrics. The daemon refuses to start instead, naming the file."""
    from vs2t_edge.runtime.wiring import load_model

    old, manifest = _deploy(tmp_path)
    (tmp_path / "c.yaml").write_text(BUNDLE_CFG)
    cfg = load_config(tmp_path / "c.yaml")
    # calibrate-threshold's file as written before it named its bundle: only the bundle's own beta
    op.write_beta_override(op.override_path_for(old), {"beta": 1234.5, "objective": "test"},
                           bundle_beta=manifest["beta"], source="test")
    assert load_model(cfg).beta == 1234.5  # the bundle it was written for takes it
    _deploy(tmp_path, beta=manifest["beta"] * 3)  # a new export deployed to the same folder
    with pytest.raises(op.OverrideFileError, match=r"bundle.beta_override.json: calibrated for another bundle"):
        load_model(cfg)


def test_an_override_names_its_bundle_and_only_that_bundle_takes_it(tmp_path):
    """calibrate-threshold's file names the bundle's seal: a re-export with the very same beta is
    still another router, and is refused; the bundle it was written for takes it."""
    from vs2t_edge.runtime.wiring import load_model

    old, manifest = _deploy(tmp_path)
    (tmp_path / "c.yaml").write_text(BUNDLE_CFG)
    cfg = load_config(tmp_path / "c.yaml")
    op.write_beta_override(op.override_path_for(old), {"beta": 1234.5, "objective": "test"},
                           bundle_beta=manifest["beta"], source="test", bundle_seal=manifest["manifest_sha256"])
    assert load_model(cfg).beta == 1234.5
    assert op.resolve_beta(cfg) == (1234.5, str(op.override_path_for(old)))  # no bundle given: not judged
    _deploy(tmp_path, note="re-exported, same beta")
    with pytest.raises(op.OverrideFileError, match=r"calibrated for another bundle \(written for manifest_sha256 "
                                                   + manifest["manifest_sha256"][:12]):
        load_model(cfg)
    # the config's own number reads no file: it stands whatever the file says
    (tmp_path / "c.yaml").write_text(BUNDLE_CFG + "beta_override: 99.0\n")
    assert load_model(load_config(tmp_path / "c.yaml")).beta == 99.0


def test_a_one_fabric_scene_needs_a_bundle_that_can_refuse_a_piece(tmp_path):
    """Restricted to one fabric, a bundle's posterior is 1 for it on every press: without the scene
    model's off-scene rules (decision.npz) nothing can send a piece to the reject bin, so every
    other fabric on the line was sorted into that fabric's bin, confident, at the first press. The
    daemon refuses the pair; two fabrics, or a bundle with a scene model, start."""
    from vs2t_edge.runtime.evidence import Evidence
    from vs2t_edge.runtime.wiring import load_model

    ev = Evidence(["f00"], 0.99, 5)  # what the cell's evidence made of a press that is surely not f00
    assert ev.add(SimpleNamespace(log_posterior={"f00": -1e30, "f02": 0.0})).label == "f00"
    _deploy(tmp_path)
    (tmp_path / "c.yaml").write_text(BUNDLE_CFG.replace(", {name: f02, kind: touched, bin: 2}", ""))
    with pytest.raises(ValueError, match=r"one fabric \(f00\).*no scene model.*every piece"):
        load_model(load_config(tmp_path / "c.yaml"))
    (tmp_path / "c.yaml").write_text(BUNDLE_CFG)
    assert load_model(load_config(tmp_path / "c.yaml")).scene_model is None  # two fabrics: it starts


def test_a_one_fabric_scene_needs_an_off_scene_rule_of_the_scene_model(tmp_path):
    """A scene model refuses a piece of a one-fabric scene only by its off-scene rules; training may
    turn both off (open_threshold and known_margin infinite: a choice for scenes of several fabrics,
    where the posterior itself can reject). With both off, every piece - another bundle fabric or one
    never seen - went to the one fabric's bin, and the job check said every fabric sorts."""
    import math
    from dataclasses import replace

    from vs2t_edge.runtime.scene_model import SceneModel
    from vs2t_edge.runtime.sorting import scene_model_presses
    from vs2t_edge.runtime.wiring import check_scene_against_bundle, evidence_factory_for

    means = np.array([[0.0, 0, 0], [8, 0, 0], [0, 8, 0]])
    sm = SceneModel(("f00", "f02", "f03"), frozenset({"f03"}), np.zeros(6), np.eye(6)[:, :3], means,
                    open_threshold=math.inf, known_margin=math.inf, confidence=0.99, untouched_confidence=0.99)
    model = SimpleNamespace(touched=["f00", "f02"], untouched=["f03"], scene_model=sm,
                            manifest={"provenance": {"trained": True}})
    (tmp_path / "c.yaml").write_text(BUNDLE_CFG.replace(", {name: f02, kind: touched, bin: 2}", ""))
    cfg = load_config(tmp_path / "c.yaml")
    x = np.zeros((5, 6))
    x[:, 1] = 8.0  # presses at f02's mean: surely not f00
    ev = evidence_factory_for(cfg, model)()
    assert ev.add(scene_model_presses(sm, x)[0]).label == "f00"  # what the cell would have done
    with pytest.raises(ValueError, match=r"one fabric \(f00\).*both off-scene rules off.*every piece"):
        check_scene_against_bundle(cfg, model)
    for rule in ({"open_threshold": 40.0}, {"known_margin": 0.0}):  # either rule can refuse: it starts
        check_scene_against_bundle(cfg, SimpleNamespace(**{**vars(model), "scene_model": replace(sm, **rule)}))
    (tmp_path / "c.yaml").write_text(BUNDLE_CFG)
    check_scene_against_bundle(load_config(tmp_path / "c.yaml"), model)  # two fabrics: the posterior can reject


def test_a_one_fabric_scene_is_refused_before_the_start_and_labels_keep_its_off_scene_rule(tmp_path, capsys):
    """`validate-config --check-bundle` says what the start refuses - a one-fabric scene whose scene
    model refuses nothing - from the decision file alone. With operator labels, the rule a first
    label switches to (a sum-rule bundle's stored offset setting) may have had both off-scene rules
    off: it keeps the bundle's (``SceneModel.for_labels``), so a one-fabric job with labels never
    turns into one that sorts every piece into its bin."""
    import math

    from vs2t_edge.cli import main
    from vs2t_edge.runtime.scene_model import SceneModel
    from vs2t_edge.runtime.wiring import check_scene_against_bundle

    off = {"press_var": 1.0, "offset_var_touched": 0.1, "offset_var_untouched": 20.0, "item_temperature": 1.0,
           "item_bias": 0.0, "known_margin": math.inf, "open_threshold": math.inf, "confidence": 0.9,
           "untouched_confidence": 0.9}
    means = np.array([[0.0, 0, 0], [8, 0, 0], [0, 8, 0]])
    sm = SceneModel(("f00", "f02", "f03"), frozenset({"f03"}), np.zeros(6), np.eye(6)[:, :3], means,
                    known_margin=0.0, confidence=0.99, untouched_confidence=0.99, labels_rule=off)
    model = SimpleNamespace(touched=["f00", "f02"], untouched=["f03"], scene_model=sm,
                            manifest={"provenance": {"trained": True}})
    one = BUNDLE_CFG.replace(", {name: f02, kind: touched, bin: 2}", "")
    (tmp_path / "c.yaml").write_text(one + "evidence: {operator_labels: labels.jsonl}\n")
    check_scene_against_bundle(load_config(tmp_path / "c.yaml"), model)  # its margin refuses, and labels keep it
    assert sm.for_labels().known_margin == 0.0 and sm.for_labels().open_threshold == math.inf
    (tmp_path / "bundle").mkdir()
    (tmp_path / "bundle" / "manifest.json").write_text(json.dumps({"format": "vs2t-bundle", "format_version": 2,
                                                                   "classes": {"touched": ["f00", "f02"],
                                                                               "untouched": ["f03"]},
                                                                   "decision": {"file": "decision.npz"}}))
    np.savez(tmp_path / "bundle" / "decision.npz", **sm.to_params())
    assert main(["validate-config", str(tmp_path / "c.yaml"), "--check-bundle"]) == 0
    capsys.readouterr()
    np.savez(tmp_path / "bundle" / "decision.npz", **SceneModel(
        sm.classes, sm.untouched, sm.center, sm.basis, sm.means, confidence=0.99, untouched_confidence=0.99).to_params())
    (tmp_path / "c.yaml").write_text(one)  # both rules off: what the start refuses, said before it
    assert main(["validate-config", str(tmp_path / "c.yaml"), "--check-bundle"]) == 2
    assert "one fabric (f00)" in capsys.readouterr().err


def test_confidence_null_is_no_written_confidence(tmp_path):
    """``evidence.confidence: null`` loads as the default 0.9; counted as written, it replaced the
    scene model's fitted touched confidence (0.97 here) with 0.9: a bolder cell nobody chose."""
    cfg = _cfg(tmp_path, "evidence: {confidence: null}\n")
    assert cfg.confidence == 0.9 and not op.config_sets_confidence(cfg)
    assert op.scene_model_settings(cfg, _SCENE)[0] == 0.97
    assert op.config_sets_confidence(_cfg(tmp_path, "evidence: {confidence: 0.9}\n"))
    # written with nothing after the colon (block style) it is the same null, not a YAML error
    empty = _cfg(tmp_path, "evidence:\n  confidence:\n")
    assert empty.confidence == 0.9 and not op.config_sets_confidence(empty)


def _run_daemon_on(cfg):
    """The real daemon code on ``cfg`` with fake devices and nothing to sort: (exit code, log)."""
    from vs2t_edge.runtime.daemon import run_daemon
    from vs2t_edge.runtime.items import ContinuousFeed
    from vs2t_edge.runtime.notify import Notifier
    from vs2t_edge.sim.fake_devices import FakeArm, FakeGate
    from cell_fakes import ScriptedCamera

    arm = FakeArm(config=cfg.arm)
    said: list[str] = []
    code = run_daemon(cfg, camera=ScriptedCamera(arm, []), arm=arm, gate=FakeGate(),
                      items=ContinuousFeed(limit=0), notifier=Notifier(address=""), max_items=0,
                      install_signals=False, log=said.append)
    return code, "\n".join(said)


def test_a_bundle_without_a_scene_model_is_refused_at_start_unless_the_config_opts_in(tmp_path):
    """Without its scene model (decision.npz) a bundle has no off-scene rule: a piece of a fabric
    outside the scene went to the likeliest scene fabric's bin (the bench: 41.1 % of pieces
    mis-sorted on that posterior). The daemon refuses it at start, naming the bundle and the fix,
    before any device is touched; `evidence.without_scene_model: allow` is the written opt-in."""
    from vs2t_edge.runtime.config import ConfigError

    _deploy(tmp_path)
    (tmp_path / "c.yaml").write_text(BUNDLE_CFG)
    cfg = load_config(tmp_path / "c.yaml")
    assert cfg.without_scene_model == "refuse"
    code, said = _run_daemon_on(cfg)
    assert code == 2
    assert f"bundle {cfg.bundle} has no scene model (decision.npz)" in said
    assert "vs2t-edge export RUN" in said and "evidence.without_scene_model: allow" in said
    assert not (tmp_path / "j.jsonl").exists() or "start" not in (tmp_path / "j.jsonl").read_text()
    (tmp_path / "c.yaml").write_text(BUNDLE_CFG + "evidence: {without_scene_model: allow}\n")
    code, said = _run_daemon_on(load_config(tmp_path / "c.yaml"))
    assert code == 0, said
    (tmp_path / "c.yaml").write_text(BUNDLE_CFG + "evidence: {without_scene_model: yes}\n")
    with pytest.raises(ConfigError, match=r"c.yaml:\d+: evidence.without_scene_model = True: must be"):
        load_config(tmp_path / "c.yaml")


def test_the_shipped_config_sorts_at_the_scene_models_own_confidence():
    """systemd/cell.yaml wrote `evidence.confidence: 0.95`, which overrode the touched confidence
    training chose for the mis-sort target on every cell deployed from it (0.97 or 0.99 on some
    worlds: bolder there)."""
    from pathlib import Path

    cfg = load_config(Path(__file__).parents[1] / "systemd" / "cell.yaml")
    assert not op.config_sets_confidence(cfg)
    scene = SimpleNamespace(confidence=0.99)
    assert op.confidence_override_note(cfg, scene) == ""
    assert op.scene_model_settings(cfg, SimpleNamespace(**{**vars(_SCENE), "confidence": 0.99}))[0] == 0.99


_SCENE = SimpleNamespace(confidence=0.97, untouched_confidence=0.9, evidence_weight=0.25, open_threshold=40.0,
                         known_margin=0.0, untouched=frozenset({"wool"}), item_rule="sum", refuse_early=True,
                         outlier_ratio=math.inf, classes=("denim", "wool"), known_only=())


def test_a_written_confidence_says_how_it_moves_the_operating_point(tmp_path):
    assert op.confidence_override_note(_cfg(tmp_path), _SCENE) == ""  # not written: the model's decides
    bold = op.confidence_override_note(_cfg(tmp_path, "evidence: {confidence: 0.9}\n"), _SCENE)
    assert "evidence.confidence 0.9 overrides the touched confidence 0.97" in bold and "wrong bins" in bold
    careful = op.confidence_override_note(_cfg(tmp_path, "evidence: {confidence: 0.99}\n"), _SCENE)
    assert "more cautious" in careful and "reject bin" in careful
    assert op.confidence_override_note(_cfg(tmp_path, "evidence: {confidence: 0.97}\n"), _SCENE) == ""
    assert op.confidence_override_note(_cfg(tmp_path, "evidence: {confidence: 0.9}\n"), None) == ""


def test_the_untouched_confidence_is_the_operators_knob_too(tmp_path):
    """``evidence.untouched_confidence`` sets the posterior that sorts into an untouched class (the
    knob that trades untouched pieces in their bin for fewer mis-sorts; training's report prices it):
    every untouched class of the scene model's rule, and of a model labels adapted, takes it; the
    touched confidence stays the model's; the start log says which way it moves."""
    scene = SimpleNamespace(confidence=0.97, untouched_confidence=0.9, evidence_weight=0.25, open_threshold=40.0,
                            known_margin=0.0, untouched=frozenset({"wool", "felt"}), item_rule="sum",
                            refuse_early=False, outlier_ratio=math.inf, classes=("denim", "wool", "felt"), known_only=())
    cfg = _cfg(tmp_path, "evidence: {untouched_confidence: 0.99}\n")
    assert cfg.untouched_confidence == 0.99 and _cfg(tmp_path).untouched_confidence is None
    confidence, opts = op.evidence_settings(cfg, SimpleNamespace(scene_model=scene))
    assert confidence == 0.97 and opts["class_confidence"] == {"wool": 0.99, "felt": 0.99}
    assert op.scene_model_settings(cfg, scene)[1]["class_confidence"] == {"wool": 0.99, "felt": 0.99}
    assert op.evidence_settings(_cfg(tmp_path), SimpleNamespace(scene_model=scene))[1]["class_confidence"] == \
        {"wool": 0.9, "felt": 0.9}
    note = op.confidence_override_note(cfg, scene)
    assert "evidence.untouched_confidence 0.99 overrides the untouched confidence 0.9" in note and "reject bin" in note
    both = op.confidence_override_note(_cfg(tmp_path, "evidence: {confidence: 0.9, untouched_confidence: 0.5}\n"),
                                       scene)
    assert both.count("overrides") == 2 and "wrong bins" in both
    # a bundle without a scene model has no untouched confidence: the key is said to do nothing
    assert "untouched_confidence 0.99 does nothing" in op.confidence_override_note(cfg, None)
    assert op.confidence_override_note(_cfg(tmp_path), None) == ""
    from vs2t_edge.runtime.config import ConfigError

    with pytest.raises(ConfigError, match="evidence.untouched_confidence"):
        _cfg(tmp_path, "evidence: {untouched_confidence: 1.5}\n")


def test_validate_config_warns_when_the_config_overrides_the_models_confidence(tmp_path, capsys):
    import numpy as np
    from feedback_fakes import MANIFEST_CLASSES, scene_model

    from vs2t_edge.cli import main
    from vs2t_edge.sim.scene import fake_cell_yaml

    (tmp_path / "bundle").mkdir()
    (tmp_path / "bundle" / "manifest.json").write_text(json.dumps({"format": "vs2t-bundle", "format_version": 2,
                                                                   "classes": MANIFEST_CLASSES,
                                                                   "decision": {"file": "decision.npz"}}))
    np.savez(tmp_path / "bundle" / "decision.npz", **scene_model(confidence=0.99).to_params())
    cfg = tmp_path / "cell.yaml"
    cfg.write_text(fake_cell_yaml(fabrics=(("denim", "touched", 1), ("silk", "touched", 2), ("wool", "untouched", 3)),
                                  evidence={"confidence": 0.95}))
    assert main(["validate-config", str(cfg), "--check-bundle"]) == 0  # a warning, not a refusal
    out = capsys.readouterr()
    assert "warning:" in out.err and "overrides the touched confidence 0.99" in out.err
    assert "confidence 0.95" in out.out
    cfg.write_text(fake_cell_yaml(fabrics=(("denim", "touched", 1), ("silk", "touched", 2), ("wool", "untouched", 3))))
    assert main(["validate-config", str(cfg), "--check-bundle"]) == 0
    out = capsys.readouterr()
    assert "warning" not in out.err and "confidence the scene model's" in out.out
    # a decision file the bundle's load would refuse is said so, not taken for "no scene model"
    np.savez(tmp_path / "bundle" / "decision.npz", **{**scene_model().to_params(), "outlier_ratio": 0.5})
    cfg.write_text(fake_cell_yaml(fabrics=(("denim", "touched", 1), ("silk", "touched", 2), ("wool", "untouched", 3)),
                                  evidence={"untouched_confidence": 0.99}))
    assert main(["validate-config", str(cfg), "--check-bundle"]) == 2
    out = capsys.readouterr()
    assert "decision.npz unreadable" in out.err and "outlier_ratio" in out.err and "does nothing" not in out.err


def test_the_service_says_at_start_that_its_config_overrides_the_models_confidence(tmp_path):
    from feedback_fakes import PieceModel, scene_model

    from vs2t_edge.runtime.daemon import run_daemon
    from vs2t_edge.runtime.notify import Notifier
    from vs2t_edge.sim.scene import fake_cell_yaml

    (tmp_path / "state").write_text("a file where the journal's folder should be")  # stops the start after the log
    (tmp_path / "cell.yaml").write_text(fake_cell_yaml(
        fabrics=(("denim", "touched", 1), ("silk", "touched", 2), ("wool", "untouched", 3)),
        evidence={"confidence": 0.95}, journal="state/journal.jsonl"))
    cfg = load_config(tmp_path / "cell.yaml")
    model = PieceModel()
    model.scene_model = scene_model(confidence=0.99)
    logged: list[str] = []
    assert run_daemon(cfg, model=model, notifier=Notifier(""), install_signals=False, log=logged.append) == 2
    assert any("evidence.confidence 0.95 overrides the touched confidence 0.99" in line and "wrong bins" in line
               for line in logged), logged
