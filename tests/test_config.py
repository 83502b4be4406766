"""Cell config: every key known, bounds checked, each problem named with file and line."""

from __future__ import annotations

import re
import textwrap

import pytest

from vs2t_edge.cli import main
from vs2t_edge.runtime.config import ConfigError, load_config, schema_reference, spread_order

GOOD = """\
bundle: bundle
threads: 1
devices:
  camera: {kind: sim, path: data}
  arm:
    kind: fake
    force_n: 15.0
  gate: {kind: fake}
scene:
  reject_bin: 0
  fabrics:
    - {name: denim, kind: touched, bin: 1}
    - {name: silk, kind: untouched, bin: 2}
evidence:
  confidence: 0.95
  max_presses: 6
journal: state/journal.jsonl
"""


def write(tmp_path, text, name="cell.yaml"):
    p = tmp_path / name
    p.write_text(textwrap.dedent(text))
    return p


def test_good_config_loads_with_relative_paths_resolved(tmp_path):
    cfg = load_config(write(tmp_path, GOOD))
    assert cfg.bundle == tmp_path / "bundle" and cfg.journal == tmp_path / "state/journal.jsonl"
    assert cfg.fault_file == tmp_path / "state/FAULT"
    assert cfg.bin_for("silk") == 2 and cfg.bin_for("unknown") == 0 and cfg.bin_for("tweed") == 0
    assert cfg.arm.force_n == 15.0 and cfg.max_presses == 6
    assert len(cfg.press_points_mm()) == 225 and cfg.grid_points[0] == 112  # centre first


@pytest.mark.parametrize("edit, line, words", [
    (("threads: 1", "threads: 0"), 2, "threads = 0: must be between 1 and 64"),
    (("threads: 1", "threads: 1\nthreds: 2"), 3, "threds: unknown key"),
    (("force_n: 15.0", "force_n: 99"), 7, "devices.arm.force_n = 99"),
    (("force_n: 15.0", "forse_n: 15"), 7, "devices.arm.forse_n: unknown key"),
    (("kind: untouched, bin: 2", "kind: untuoched, bin: 2"), 13, "must be touched or untouched"),
    (("kind: untouched, bin: 2", "kind: untouched, bin: 0"), 13, "that is the reject bin"),
    (("confidence: 0.95", "confidence: high"), 15, "confidence = 'high': must be a number"),
    (("max_presses: 6", "max_presses: 500"), 16, "max_presses = 500"),
    (("camera: {kind: sim, path: data}", "camera: {kind: webcam}"), 4, "must be one of uvc, replay, sim"),
    (("bundle: bundle\n", ""), None, "bundle: required"),
])
def test_each_problem_names_file_line_and_key(tmp_path, edit, line, words):
    text = GOOD.replace(*edit)
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    msg = str(info.value)
    assert words in msg
    if line is not None:
        assert f"{path}:{line}:" in msg


@pytest.mark.parametrize("edit, words", [
    ("grid_step_x_mm: 10", "devices.arm.grid_step_x_mm = 10: the 15 x 15 press grid would span 140 mm, more "
                           "than the 80 mm piece (piece_mm); at most 5.714 mm"),
    ("piece_yaw_rad: .nan", "devices.arm.piece_yaw_rad = nan: must be between"),
    ("reconnect_attempts: 2.5", "devices.arm.reconnect_attempts = 2.5: must be a whole number"),
])
def test_arm_geometry_and_counts_are_refused_at_load_naming_the_line(tmp_path, edit, words, capsys):
    """Each of these passed validate-config before; the grid one then crashed the daemon in
    SceneSpec.from_config (press_grid_mm's ValueError)."""
    path = write(tmp_path, GOOD.replace("    force_n: 15.0\n", f"    force_n: 15.0\n    {edit}\n"))
    assert main(["validate-config", str(path)]) == 2
    assert f"{path}:8: {words}" in capsys.readouterr().err


def test_the_widest_grid_that_fits_loads_and_builds_the_scene(tmp_path):
    from vs2t_edge.runtime.cell import SceneSpec

    path = write(tmp_path, GOOD.replace("    force_n: 15.0\n", "    force_n: 15.0\n    grid_step_x_mm: 5.714\n"))
    points = SceneSpec.from_config(load_config(path)).points_mm
    xs = sorted({x for x, _ in points})
    assert len(points) == 225 and xs[0] >= 0.0 and xs[-1] <= 80.0


def test_all_problems_reported_at_once(tmp_path):
    text = GOOD.replace("threads: 1", "threads: 0").replace("max_presses: 6", "max_presses: 0")
    with pytest.raises(ConfigError) as info:
        load_config(write(tmp_path, text))
    assert len(info.value.problems) == 2


def test_duplicate_fabric_and_broken_yaml(tmp_path):
    text = GOOD.replace("name: silk", "name: denim")
    with pytest.raises(ConfigError, match="listed twice"):
        load_config(write(tmp_path, text))
    with pytest.raises(ConfigError, match=r"cell.yaml:\d+: not valid YAML"):
        load_config(write(tmp_path, "bundle: [unclosed\n"))


def test_a_fabric_named_like_a_stranger_the_operator_teaches_is_refused(tmp_path):
    """A stranger the operator labels off-scene is the class 'off-scene:NAME' (runtime/feedback.py),
    decided like any class and sent, being no job fabric, to the reject bin. A job fabric of that
    name would be the same class: the stranger's pieces into that fabric's bin (and the fabric
    trusted as taught, unguarded by the zero-shot rule)."""
    text = GOOD.replace("name: silk", "name: 'off-scene:silk'")
    with pytest.raises(ConfigError, match="'off-scene:' is reserved"):
        load_config(write(tmp_path, text))


@pytest.mark.parametrize("first, second", [("denim", "Denim"), ("denim", "'de nim'"),
                                           ("caf\u00e9", "cafe\u0301")])  # NFC and NFD of one word
def test_two_fabrics_one_name_to_a_label_are_refused(tmp_path, first, second):
    """A label names a fabric as typed, case, Unicode form and spaces set aside (runtime/labels.py):
    fabrics 'denim' and 'Denim' in one job would take each other's labels - a piece taught into the
    other's bin."""
    text = GOOD.replace("name: denim", f"name: {first}").replace("name: silk", f"name: {second}")
    with pytest.raises(ConfigError, match="the same name to a person"):
        load_config(write(tmp_path, text))


def test_list_order_checks_indices(tmp_path):
    text = GOOD.replace("max_presses: 6", "max_presses: 2\n  grid_order: list\n  grid_points: [3, 300]")
    with pytest.raises(ConfigError, match=r"\[300\] are not grid indices"):
        load_config(write(tmp_path, text))
    ok = load_config(write(tmp_path, GOOD.replace("max_presses: 6", "max_presses: 2\n  grid_order: list\n"
                                                                    "  grid_points: [3, 7]")))
    assert ok.grid_points == (3, 7)


def test_spread_order_is_a_permutation_far_points_first():
    order = spread_order()
    assert sorted(order) == list(range(225))
    assert order[0] == 112 and order[1] in (0, 14, 210, 224)


def test_validate_config_cli_exit_codes(tmp_path, capsys):
    assert main(["validate-config", str(write(tmp_path, GOOD))]) == 0
    assert "ok" in capsys.readouterr().out
    bad = write(tmp_path, GOOD.replace("threads: 1", "threads: -3"), "bad.yaml")
    assert main(["validate-config", str(bad)]) == 2
    assert f"{bad}:2: threads = -3" in capsys.readouterr().err
    assert main(["validate-config", str(tmp_path / "missing.yaml")]) == 2


def test_validate_config_check_bundle_refuses_a_bundle_without_scene_model(tmp_path, capsys):
    """The unit's ExecStartPre says what `run` would refuse: a bundle with no scene model, unless the
    config opts in (evidence.without_scene_model: allow)."""
    import json

    (tmp_path / "bundle").mkdir()
    (tmp_path / "bundle" / "manifest.json").write_text(json.dumps({"format": "vs2t-bundle", "format_version": 2}))
    path = write(tmp_path, GOOD)
    assert main(["validate-config", str(path), "--check-bundle"]) == 2
    assert "no scene model" in capsys.readouterr().err
    assert main(["validate-config", str(path)]) == 0  # without --check-bundle the bundle is not read
    (tmp_path / "bundle" / "manifest.json").write_text(json.dumps({"format": "vs2t-bundle", "format_version": 2,
                                                                   "decision": {"file": "decision.npz"}}))
    assert main(["validate-config", str(path), "--check-bundle"]) == 2  # listed, not there: the load refuses it
    assert "decision.npz unreadable" in capsys.readouterr().err
    import numpy as np
    from feedback_fakes import scene_model

    sm = scene_model(untouched=frozenset({"silk"}))  # GOOD's kinds: denim touched, silk untouched
    np.savez(tmp_path / "bundle" / "decision.npz", **sm.to_params())
    (tmp_path / "bundle" / "manifest.json").write_text(json.dumps({
        "format": "vs2t-bundle", "format_version": 2, "classes": {"touched": ["denim", "wool"], "untouched": ["silk"]},
        "decision": {"file": "decision.npz"}}))
    assert main(["validate-config", str(path), "--check-bundle"]) == 0


def test_validate_config_check_bundle_refuses_every_job_the_start_refuses(tmp_path, capsys):
    """The unit's ExecStartPre (`validate-config --check-bundle`) passed jobs that `run` then
    refused at start: a fabric the bundle lacks or spells otherwise, one it knows only to refuse,
    a kind the bundle disagrees with, an untrained bundle. Each is now said before the start, from
    the bundle's files, by the same function the start asks (runtime/operating_point.py)."""
    import json
    from types import SimpleNamespace

    import numpy as np
    from feedback_fakes import scene_model

    from vs2t_edge.runtime.wiring import check_scene_against_bundle

    (tmp_path / "bundle").mkdir()
    sm = scene_model(untouched=frozenset({"silk"}), known_only=("wool",))
    np.savez(tmp_path / "bundle" / "decision.npz", **sm.to_params())
    classes = {"touched": ["denim"], "untouched": ["silk"]}
    cases = [("denim", "touched", {}, None),
             ("Denim", "touched", {}, "scene fabric(s) ['Denim'] are not classes of bundle"),
             ("linen", "touched", {}, "scene fabric(s) ['linen'] are not classes of bundle"),
             ("wool", "touched", {}, "known to bundle"),
             ("denim", "untouched", {}, "scene fabric kind disagrees with bundle"),
             ("denim", "touched", {"provenance": {"trained": False}}, "was never trained")]
    for name, kind, extra, refusal in cases:
        (tmp_path / "bundle" / "manifest.json").write_text(json.dumps(
            {"format": "vs2t-bundle", "format_version": 2, "classes": classes, "decision": {"file": "decision.npz"},
             **extra}))
        path = write(tmp_path, GOOD.replace("{name: denim, kind: touched, bin: 1}",
                                            f"{{name: {name}, kind: {kind}, bin: 1}}"))
        code = main(["validate-config", str(path), "--check-bundle"])
        err = capsys.readouterr().err
        assert code == (0 if refusal is None else 2), (name, kind, extra, err)
        loaded = SimpleNamespace(touched=classes["touched"], untouched=classes["untouched"], scene_model=sm,
                                 manifest=extra)
        if refusal is None:
            check_scene_against_bundle(load_config(path), loaded)
            continue
        assert refusal in err, err
        with pytest.raises(ValueError, match=re.escape(refusal)):
            check_scene_against_bundle(load_config(path), loaded)  # what the start says, word for word
    (tmp_path / "bundle" / "manifest.json").write_text(json.dumps(
        {"format": "vs2t-bundle", "format_version": 2, "classes": {"touched": "denim"},
         "decision": {"file": "decision.npz"}}))
    assert main(["validate-config", str(write(tmp_path, GOOD)), "--check-bundle"]) == 2
    assert "'classes.touched' must be a list of class names" in capsys.readouterr().err


def test_docs_reference_lists_every_key():
    from pathlib import Path

    doc = (Path(__file__).parents[1] / "docs" / "cell.md").read_text()
    for key, _default, _bounds, _help in schema_reference():
        assert f"`{key}`" in doc, f"docs/cell.md does not document config key {key}"


def test_alias_bombs_and_self_reference_are_refused(tmp_path):
    bomb = "a: &a [x, x, x, x, x, x, x, x, x, x]\n" + "".join(
        f"{c}: &{c} [*{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}]\n"
        for p, c in zip("abcdefg", "bcdefgh"))
    with pytest.raises(ConfigError, match="too large"):
        load_config(write(tmp_path, bomb))


from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

_yaml_ish = st.recursive(
    st.none() | st.booleans() | st.integers(-10**6, 10**6) | st.floats(allow_nan=True) | st.text(max_size=20),
    lambda kids: st.lists(kids, max_size=4) | st.dictionaries(
        st.sampled_from(["bundle", "threads", "devices", "camera", "arm", "gate", "kind", "scene", "fabrics",
                         "name", "bin", "evidence", "grid_points", "grid_order", "max_presses", "force_n",
                         "piece_origin_pose", "journal", "watchdog", "x"]), kids, max_size=5),
    max_leaves=25)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(doc=_yaml_ish)
def test_any_yaml_document_gives_a_config_or_a_config_error(tmp_path, doc):
    import yaml

    path = tmp_path / "fuzz.yaml"
    path.write_text(yaml.safe_dump(doc))
    try:
        load_config(path)
    except ConfigError as exc:
        assert all(p.startswith(str(path)) for p in exc.problems)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(text=st.text(max_size=200))
def test_any_text_gives_a_config_error_not_a_crash(tmp_path, text):
    path = tmp_path / "fuzz.yaml"
    path.write_bytes(text.encode("utf-8", "surrogatepass"))
    with pytest.raises(ConfigError):
        load_config(path)


def test_defaults_are_typed(tmp_path):
    from pathlib import Path

    cfg = load_config(write(tmp_path, GOOD.replace("journal: state/journal.jsonl\n", "")))
    assert cfg.journal == Path("/var/lib/vs2t-edge/journal.jsonl") and cfg.fault_file.name == "FAULT"
    assert isinstance(cfg.camera["fps"], float)


def test_contact_check_is_on_for_a_live_sensor_and_off_for_replays_unless_asked(tmp_path):
    from vs2t_edge.runtime.config import load_config
    from vs2t_edge.runtime.wiring import contact_check_for

    def cfg(camera: str):
        p = tmp_path / "c.yaml"
        p.write_text("bundle: b\ndevices:\n  camera: " + camera + "\n  gate: {kind: fake}\n  arm: {kind: fake}\n"
                     "scene:\n  reject_bin: 0\n  fabrics:\n    - {name: denim, kind: touched, bin: 1}\n")
        p.chmod(0o640)
        return load_config(p)

    live = contact_check_for(cfg("{kind: uvc}"))
    assert live is not None and live.threshold_levels == 12.0 and live.min_area_fraction == 0.005
    assert contact_check_for(cfg("{kind: replay, path: x.replay}")) is None
    forced = contact_check_for(cfg("{kind: replay, path: x.replay, contact_check: 'on', contact_threshold_levels: 4}"))
    assert forced is not None and forced.threshold_levels == 4.0
    assert contact_check_for(cfg("{kind: uvc, contact_check: 'off'}")) is None


def test_the_reject_bin_is_the_bin_the_gate_fails_safe_to(tmp_path):
    """The gate puts its flap at bin 0 on its own (firmware GATE_REJECT_BIN, protocol.REJECT_BIN):
    the cell's to_reject on every latched fault and SIGTERM abort, the heartbeat fail-safe, a boot
    and a clear. A config with another reject bin and a fabric on bin 0 passed validation: every
    piece in hand at a fault then fell into that fabric's bin (a mis-sort) while its final record
    said 'reject bin 7'. Any other reject bin is refused, naming the line."""
    path = write(tmp_path, GOOD.replace("reject_bin: 0", "reject_bin: 7").replace("bin: 1}", "bin: 0}"))
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert f"{path}:10: scene.reject_bin = 7: the gate's own reject bin is 0" in str(info.value)
    path = write(tmp_path, GOOD.replace("reject_bin: 0", "reject_bin: 3"))
    with pytest.raises(ConfigError, match="scene.reject_bin = 3: the gate's own reject bin is 0"):
        load_config(path)


def test_two_fabrics_in_one_bin_while_bins_are_free_is_refused_unless_allowed(tmp_path, capsys):
    """A copied line that gives silk denim's bin sorts every silk piece into denim's bin: refused
    while a bin stays free, naming the fabrics, the bin and the key that allows it; allowed when
    written (scene.shared_bins: allow), and needed by no job with more fabrics than the gate's bins."""
    assert load_config(write(tmp_path, GOOD)).fabrics
    merged = GOOD.replace("kind: untouched, bin: 2", "kind: untouched, bin: 1")
    path = write(tmp_path, merged)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert "denim and silk share bin 1, while bin(s) [2, 3, 4, 5, 6, 7] stay free" in str(info.value)
    assert "scene.shared_bins: allow" in str(info.value) and f"{path}:" in str(info.value)
    assert main(["validate-config", str(path)]) == 2
    assert "denim and silk share bin 1" in capsys.readouterr().err
    allowed = write(tmp_path, merged.replace("  reject_bin: 0\n", "  reject_bin: 0\n  shared_bins: allow\n"))
    cfg = load_config(allowed)
    assert cfg.bin_for("silk") == cfg.bin_for("denim") == 1
    assert main(["validate-config", str(allowed)]) == 0 and "share" not in capsys.readouterr().err
    full = GOOD.replace("    - {name: silk, kind: untouched, bin: 2}\n",
                        "".join(f"    - {{name: f{b}, kind: touched, bin: {b}}}\n" for b in range(2, 8))
                        + "    - {name: silk, kind: untouched, bin: 1}\n")
    assert load_config(write(tmp_path, full)).bin_for("silk") == 1  # every bin used: sharing is needed


def test_the_state_files_are_four_files(tmp_path):
    """A fault file that is the journal: the first latched fault replaced every decision record with
    the fault's text, and clearing the fault deleted the journal. The journal, the fault file, the
    labels file and the beta override file must each be a file of its own, named with its line."""
    path = write(tmp_path, GOOD + "fault_file: state/journal.jsonl\n")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert f"{path}:{GOOD.count(chr(10)) + 1}: fault_file: " in str(info.value) and "is also the journal" in str(info.value)
    labels = GOOD.replace("  max_presses: 6\n", "  max_presses: 6\n  operator_labels: state/./journal.jsonl\n")
    with pytest.raises(ConfigError, match="evidence.operator_labels: .* is also the journal"):
        load_config(write(tmp_path, labels))
    with pytest.raises(ConfigError, match=r"beta_override_file: .* is also the evidence.operator_labels"):
        load_config(write(tmp_path, labels.replace("state/./journal.jsonl", "labels.jsonl")
                          + "beta_override_file: labels.jsonl\n"))
    named_fault = GOOD.replace("journal: state/journal.jsonl", "journal: state/FAULT")
    with pytest.raises(ConfigError, match=r"fault_file: .*FAULT is also the journal \(the fault file's default"):
        load_config(write(tmp_path, named_fault))
    ok = load_config(write(tmp_path, GOOD + "fault_file: state/FAULT.txt\n"))
    assert ok.fault_file == tmp_path / "state" / "FAULT.txt"


def test_numbers_yaml_reads_otherwise_than_written_are_refused(tmp_path):
    # YAML 1.1 reads 010 as octal 8 and 1:30 as base-60 90: the cell must not run on a number the
    # person did not write; 07 (7 either way) and quoted text load as written
    for old, new, said in (
            ("max_presses: 6", "max_presses: 010", "cell.yaml:16: evidence.max_presses: 010 reads as 8 in YAML (a "
                                                   "leading 0 makes it octal; write 10 if that is meant, or 8"),
            ("max_presses: 6", "max_presses: +010", "cell.yaml:16: evidence.max_presses: +010 reads as 8 in YAML"),
            ("max_presses: 6", "max_presses: 1:30", "cell.yaml:16: evidence.max_presses: 1:30 reads as 90 in YAML "
                                                    "(a colon makes it base 60; write 90 if that is meant"),
            ("confidence: 0.95", "confidence: 1:30.5", "cell.yaml:15: evidence.confidence: 1:30.5 reads as 90.5 in "
                                                       "YAML (a colon makes it base 60"),
            ("max_presses: 6", 'max_presses: !!int "010"', "cell.yaml:16: evidence.max_presses: 010 reads as 8 in YAML"),
            ("max_presses: 6", "max_presses: !!int '1:30'", "cell.yaml:16: evidence.max_presses: 1:30 reads as 90")):
        with pytest.raises(ConfigError) as err:
            load_config(write(tmp_path, GOOD.replace(old, new)))
        (problem,) = err.value.problems
        assert said in problem, problem
    assert load_config(write(tmp_path, GOOD.replace("max_presses: 6", "max_presses: 07"))).max_presses == 7
    assert load_config(write(tmp_path, GOOD.replace("max_presses: 6", 'max_presses: !!int "07"'))).max_presses == 7
