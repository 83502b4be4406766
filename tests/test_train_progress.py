"""Training's progress lines (train/progress.py): the long loops draw them on stderr when asked or
on a terminal, as plain lines off one, and printing them changes no weight. Out of
tests/test_train.py."""

import torch

from test_train import _views
from vs2t_edge.train import compare as cmp
from vs2t_edge.train import vs2t


def _weights(*modules) -> list[torch.Tensor]:
    return [p.detach().clone() for m in modules if m is not None for p in m.state_dict().values()]


def test_generator_and_classifier_progress_reach_stderr_and_change_nothing(monkeypatch, capsys):
    """The longest steps (generator fit, CLS_u, CLS_t) draw progress on stderr when asked
    (``VS2T_PROGRESS=1``; a terminal turns it on by itself), are silent with ``VS2T_PROGRESS=0``,
    and printing it leaves the seeded weights bit-identical."""
    from vs2t_edge.train.baselines import train_classifier

    views = _views()
    budget = vs2t.VS2TBudget(steps=40, cls_steps=30, n_synth_per_class=10, hidden=32, latent=4)
    monkeypatch.setattr("sys.stderr.isatty", lambda: True, raising=False)  # drawn as on a terminal
    out = {}
    for flag in ("1", "0"):
        monkeypatch.setenv("VS2T_PROGRESS", flag)
        capsys.readouterr()
        m = vs2t.VS2TZSL().fit(views.train, budget, seed=3)
        clf = train_classifier(views.train.x_t, views.train.y, views.train.n_t, steps=20, seed=3, label="CLS_t")
        out[flag] = (_weights(m.E, m.G, m.D, m.vsf, m.cls_u, clf), capsys.readouterr().err)
    err = out["1"][1]
    assert "\rVS2T-ZSL generator: step 1/40" in err and "\rVS2T-ZSL CLS_u: step 1/30" in err, err
    assert "\rCLS_t: step 1/20" in err, err
    assert err.endswith("\r"), "the progress line is erased when the loop ends"
    assert out["0"][1] == ""
    a, b = out["1"][0], out["0"][0]
    assert len(a) == len(b) and all(torch.equal(x, y) for x, y in zip(a, b))


def test_every_compared_methods_fit_shows_progress(monkeypatch, capsys):
    """Each row of the comparison (compare.all_methods: the paper's baselines, the modern
    generators, VS2T-ZSL) reports its training loop on stderr under its own name."""
    from vs2t_edge.train.baselines import Budget

    monkeypatch.setenv("VS2T_PROGRESS", "1")
    monkeypatch.setattr("sys.stderr.isatty", lambda: True, raising=False)  # drawn as on a terminal
    views = _views()
    budget = Budget(steps=4, batch=16, hidden=16, latent=4, cls_steps=3, n_synth_per_class=5)
    for name, cls in cmp.all_methods().items():
        capsys.readouterr()
        cls().fit(views.train, budget, seed=0)
        err = capsys.readouterr().err
        assert f"\r{name} " in err and ": step 1/" in err, (name, err)


def test_progress_off_a_terminal_is_plain_lines_one_per_tenth(monkeypatch, capsys):
    """Carriage returns in a log file or a pipe made one very long line of every redraw; off a
    terminal progress is plain lines: a loop's first step and one per tenth after it."""
    from vs2t_edge.train import progress

    monkeypatch.setenv("VS2T_PROGRESS", "1")  # a log file asked for progress
    assert list(progress.steps(iter(range(200)), 200, "fit")) == list(range(200))
    lines = capsys.readouterr().err.splitlines(keepends=True)
    assert [ln.split(" (")[0] for ln in lines] == [f"fit: step {1 + 20 * k}/200" for k in range(10)]
    assert not any("\r" in ln for ln in lines)
    line = progress.Line()  # features.py's lines are drawn whether or not a terminal is there
    for i in range(1, 401):
        line.draw(f"features: press {i}/400", i / 400)
    line.keep()
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 11 and lines[0] == "features: press 1/400" and lines[-1] == "features: press 400/400"
    line.draw("fine-tune tactile tail: epoch 1/2", 0.5)
    line.draw("fine-tune tactile tail: epoch 2/2", 1.0)
    line.keep()
    assert capsys.readouterr().err.splitlines() == ["fine-tune tactile tail: epoch 1/2",
                                                    "fine-tune tactile tail: epoch 2/2"]


def test_progress_is_off_when_stderr_is_not_a_terminal(monkeypatch, capsys):
    from vs2t_edge.train import progress

    monkeypatch.delenv("VS2T_PROGRESS", raising=False)
    assert not progress.enabled()  # pytest's captured stderr is not a terminal
    assert list(progress.steps(iter(range(5)), 5, "x")) == [0, 1, 2, 3, 4]
    assert capsys.readouterr().err == ""
    monkeypatch.setattr("sys.stderr.isatty", lambda: True, raising=False)
    assert progress.enabled()
