"""`jaxsync train` on distributed trajectory files: flags, files, printed lines, resuming."""

import argparse
import json

import h5py
import numpy as np
import pytest

from jaxsync.cli.train import add_train_parser
from jaxsync.errors import CheckpointError, ConfigError
from jaxsync.io.surrogate_file import check_compatible, load_surrogate
from jaxsync.surrogate import (
    ArchitectureChoice,
    Sampling,
    TrainConfig,
    TrainingChecks,
    TrainingState,
    train_surrogates,
)
from oscillator_trajectories import NODES, write_trajectory


def _parser():
    parser = argparse.ArgumentParser(prog="jaxsync")
    add_train_parser(parser.add_subparsers(dest="command", required=True))
    return parser


SMALL = ["--n-s", "2", "--n-past", "6", "--n-future", "5", "--n-hidden", "6", "--n-layers", "1", "--batch-size", "8",
         "--eta0", "1e-2", "--gamma", "0.95", "--epochs", "12", "--epochs-per-call", "6", "--no-progress"]


def test_every_option_has_help():
    parser = _parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices["train"]
    for action in sub._actions:
        assert action.help, f"option {action.option_strings or action.dest} has no help text"


def test_train_writes_checkpoint_curves_and_summary(tmp_path, capsys):
    # Two runs of one partition with different loads, conditional decoder (q = 3).
    paths = []
    for k, load in enumerate((1.0, 0.6)):
        paths.append(tmp_path / f"run{k}.h5")
        write_trajectory(paths[-1], load=load)
    out = tmp_path / "out"
    args = _parser().parse_args(["train", *map(str, paths), "-o", str(out), "--cond-repeat", "3",
                                 "--emse-applications", "20", *SMALL])
    assert args.func(args) == 0

    ckpt = load_surrogate(out / "surrogate.h5")
    check_compatible(ckpt, NODES)
    assert ckpt.dof_counts == (6, 9) and ckpt.arch.n_dof == 9 and ckpt.n_s == 2
    assert ckpt.arch.n_hidden == 6 and ckpt.arch.n_past == 6 and ckpt.arch.n_future == 5
    assert ckpt.arch.n_cond_repeat == 3
    assert (out / "loss_curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    summary = json.loads((out / "train_summary.json").read_text())
    assert summary["load_parameters"] == [1.0, 0.6]
    assert summary["dof_counts"] == [6, 9] and summary["training"]["n_epochs_run"] == 12
    assert summary["sampling"]["n_train_windows"] + summary["sampling"]["n_val_windows"] == 2 * (150 - 11 + 1)
    assert summary["sampling"]["split"] == "interleaved" and ckpt.metadata["sampling"]["split"] == "interleaved"
    assert len(summary["loss_history"]["val"]) == 12 and len(summary["loss_history"]["val"][0]) == 2
    assert all(f < i for f, i in zip(summary["final_val_loss"], summary["initial_val_loss"]))
    assert summary["e_mse_applications"] == 20 and len(summary["sqrt_e_mse"]) == 2
    assert all(np.isfinite(summary["sqrt_e_mse"]))
    assert summary["seconds_per_epoch"] > 0 and summary["gradient_steps_per_second"] > 0
    assert ckpt.metadata["final_val_loss"] == summary["final_val_loss"]
    assert not [p.name for p in out.iterdir() if ".tmp" in p.name]
    printed = capsys.readouterr().out
    assert f"wrote {out / 'surrogate.h5'}, {out / 'loss_curves.png'} and train_summary.json (12 epochs)" in printed
    # the offline rollout check, printed and in the summary (a 12-epoch network misses 2 %)
    check = summary["rollout_check"]
    assert check["tolerance"] == 0.02 and check["passed"] is False and len(check["relative"]) == 2
    assert (f"offline check: rolled out over {check['n_steps']} steps, shared displacements off by up to "
            f"{100 * check['relative'][0]:.2f} %") in printed and "ABOVE the tolerance of 2 %" in printed
    # two candidates per part by default: which one each part kept, and their losses
    candidates = summary["candidates"]
    assert candidates["n_candidates"] == 2 and len(candidates["best_val_loss"]) == 2
    assert summary["final_val_loss"] == [min(c[p] for c in candidates["best_val_loss"]) for p in range(2)]
    assert (f"candidates: 2 networks per part, kept candidate {', '.join(map(str, candidates['chosen']))}"
            in printed)


def test_train_errors(tmp_path):
    sparse = tmp_path / "every5.h5"
    write_trajectory(sparse, save_every=5)
    args = _parser().parse_args(["train", str(sparse), "-o", str(tmp_path / "x"), *SMALL])
    with pytest.raises(CheckpointError, match="every 5 steps, which does not divide the sampling stride n_s=2; "
                                              "rerun the solver with shared_every dividing n_s"):
        args.func(args)

    plain = tmp_path / "plain.h5"
    write_trajectory(plain, n_steps=300)
    args = _parser().parse_args(["train", str(plain), "-o", str(tmp_path / "y"), "--cond-repeat", "2", *SMALL])
    with pytest.raises(ConfigError, match="load parameter"):
        args.func(args)

    other = tmp_path / "other.h5"
    write_trajectory(other, n_steps=300, nodes=(np.array([3, 8]), np.array([3, 9, 11])))
    args = _parser().parse_args(["train", str(plain), str(other), "-o", str(tmp_path / "z"), *SMALL])
    with pytest.raises(CheckpointError, match="another partition"):
        args.func(args)

    args = _parser().parse_args(["train", str(plain), "-o", str(tmp_path / "w"), "--load-parameter", "1", "2",
                                 "--cond-repeat", "2", *SMALL])
    with pytest.raises(ConfigError, match="2 values for 1 trajectories"):
        args.func(args)
    assert not (tmp_path / "x").exists() or not any((tmp_path / "x").iterdir())


def test_defaults_fit_a_laptop_and_agree_with_python_and_the_demo():
    from jaxsync.app.demo import DemoSettings

    args = _parser().parse_args(["train", "run.h5"])
    config = TrainConfig()
    assert (args.batch_size, args.eta0, args.gamma, args.eta_min, args.epochs, args.patience,
            args.epochs_per_call) == (config.batch_size, config.eta0, config.gamma, config.eta_min,
                                      config.n_epochs, config.patience, config.epochs_per_call)
    assert (args.n_hidden, args.n_layers, args.epochs, args.state_every, args.allow_predicted) == (
        50, 2, 800, 50, False)
    from jaxsync.app.demo import demo_defaults

    demo = demo_defaults("cantilever")
    # what the demo is not told keeps its case's default
    assert all(getattr(DemoSettings(), k) is None
               for k in ("n_hidden", "n_layers", "epochs", "eta0", "gamma", "batch_size", "n_s"))
    assert DemoSettings().applied_to(demo) == demo
    assert (demo.n_hidden, demo.n_layers, demo.epochs, demo.eta0, demo.gamma, demo.batch_size, demo.n_s) == (
        args.n_hidden, args.n_layers, args.epochs, args.eta0, args.gamma, args.batch_size, args.n_s)
    arch, sampling, checks = ArchitectureChoice(), Sampling(), TrainingChecks()
    assert (arch.n_hidden, arch.n_layers, sampling.n_s, TrainingState.every,
            checks.emse_applications) == (args.n_hidden, args.n_layers, args.n_s, args.state_every,
                                          args.emse_applications)
    assert (sampling.n_offsets, checks.rollout_tolerance) == (args.n_offsets, args.rollout_tolerance)
    assert config.n_candidates == args.n_candidates == demo.n_candidates == 2
    assert _parser().parse_args(["train", "run.h5", "--candidates", "3"]).n_candidates == 3
    assert sampling.split == args.split == "interleaved"
    assert _parser().parse_args(["train", "run.h5", "--split", "random"]).split == "random"
    assert (args.n_s, args.batch_size, args.patience) == (150, 10, 200)
    # the old spellings stay
    old = _parser().parse_args(["train", "run.h5", "--hidden", "7", "--layers", "3"])
    assert (old.n_hidden, old.n_layers) == (7, 3)
    # the paper's rule stays available
    paper = _parser().parse_args(["train", "run.h5", "--epochs", "paper", "--eta0", "5e-4", "--gamma", "0.9995"])
    assert paper.epochs is None
    assert TrainConfig(eta0=paper.eta0, gamma=paper.gamma, eta_min=paper.eta_min,
                       n_epochs=paper.epochs).resolved_epochs == 13812
    for bad in (["--epochs", "0"], ["--epochs", "many"], ["--patience", "-1"], ["--state-every", "x"]):
        with pytest.raises(SystemExit):
            _parser().parse_args(["train", "run.h5", *bad])


def test_train_resumes_after_an_interruption(tmp_path, capsys):
    path = write_trajectory(tmp_path / "run.h5", n_steps=300)
    common = ["train", str(path), *SMALL, "--state-every", "6", "--emse-applications", "0"]
    whole = _parser().parse_args([*common, "-o", str(tmp_path / "whole")])
    assert whole.func(whole) == 0

    # the library function with the settings of the command, killed right after the
    # epoch-6 state is written
    def killed(progress):
        if progress.state_written:
            raise KeyboardInterrupt

    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        train_surrogates(path, architecture=ArchitectureChoice(n_hidden=6, n_layers=1),
                         sampling=Sampling(n_s=2, n_past=6, n_future=5), checks=TrainingChecks(emse_applications=0),
                         optimizer=TrainConfig(batch_size=8, eta0=1e-2, gamma=0.95, n_epochs=12, epochs_per_call=6),
                         state=TrainingState(out, every=6), progress=False, callback=killed)
    assert (out / "training_state.h5").exists() and not (out / "surrogate.h5").exists()

    # another run into that folder, with other options, is refused ...
    other = _parser().parse_args([*common, "-o", str(out), "--eta0", "2e-2"])
    with pytest.raises(CheckpointError, match="eta0"):
        other.func(other)
    # ... the same command resumes and ends where the uninterrupted run did
    capsys.readouterr()
    args = _parser().parse_args([*common, "-o", str(out)])
    assert args.func(args) == 0
    assert f"resuming from the training state {out / 'training_state.h5'}" in capsys.readouterr().out
    summary = json.loads((out / "train_summary.json").read_text())
    assert summary["training"]["resumed_from_epoch"] == 6 and summary["n_epochs_run"] == 12
    a, b = load_surrogate(tmp_path / "whole" / "surrogate.h5"), load_surrogate(out / "surrogate.h5")
    for x, y in zip(jax_leaves(a.params), jax_leaves(b.params)):
        np.testing.assert_array_equal(x, y)
    assert summary["loss_history"] == json.loads((tmp_path / "whole" / "train_summary.json").read_text())[
        "loss_history"]
    assert not (out / "training_state.h5").exists()  # everything is written: nothing left to resume


def jax_leaves(tree):
    import jax

    return jax.tree_util.tree_leaves(tree)


def test_train_stops_early_and_reports_it(tmp_path):
    path = tmp_path / "run.h5"
    write_trajectory(path, n_steps=300)
    # a learning rate too small to move float32 parameters: no improvement after epoch 1
    args = _parser().parse_args(["train", str(path), "-o", str(tmp_path / "o"), *SMALL, "--eta0", "1e-37",
                                 "--patience", "3", "--emse-applications", "0"])
    assert args.func(args) == 0
    summary = json.loads((tmp_path / "o" / "train_summary.json").read_text())
    assert summary["stopped_at_epoch"] == 4 and summary["n_epochs_run"] == 4
    assert summary["training"]["stopped_early"] and summary["training"]["best_epoch"] == [1, 1]
    assert summary["final_val_loss"] == [row[0] for row in zip(*summary["loss_history"]["val"])]
    assert len(summary["loss_history"]["val"]) == 4


def test_train_refuses_predicted_and_foreign_files(tmp_path):
    flags = np.ones(300, bool)
    flags[100:] = False  # a synchronization-avoiding run: predicted from step 100 on
    predicted = write_trajectory(tmp_path / "online.h5", n_steps=300, synchronized=flags)
    args = _parser().parse_args(["train", str(predicted), "-o", str(tmp_path / "p"), *SMALL])
    with pytest.raises(CheckpointError, match="synchronization-avoiding.*200 of its 300.*--allow-predicted"):
        args.func(args)
    assert not (tmp_path / "p" / "surrogate.h5").exists()
    args = _parser().parse_args(["train", str(predicted), "-o", str(tmp_path / "p"), *SMALL,
                                 "--allow-predicted", "--emse-applications", "0"])
    assert args.func(args) == 0 and (tmp_path / "p" / "surrogate.h5").exists()
    # all-synchronized flags are a synchronized run
    synced = write_trajectory(tmp_path / "synced.h5", n_steps=300, synchronized=np.ones(300, bool))
    args = _parser().parse_args(["train", str(synced), "-o", str(tmp_path / "s"), *SMALL, "--emse-applications", "0"])
    assert args.func(args) == 0

    foreign = write_trajectory(tmp_path / "foreign.h5", n_steps=300)
    with h5py.File(foreign, "r+") as fh:
        del fh.attrs["format"]
    args = _parser().parse_args(["train", str(foreign), "-o", str(tmp_path / "f"), *SMALL])
    with pytest.raises(CheckpointError, match="not a jaxsync trajectory"):
        args.func(args)
