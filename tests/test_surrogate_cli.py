"""`jaxsync train` on a synthetic distributed trajectory file."""

import argparse
import json

import h5py
import numpy as np
import pytest

from jaxsync.errors import CheckpointError, ConfigError
from jaxsync.surrogate.checkpoint import check_compatible, load_checkpoint
from jaxsync.surrogate.cli import add_train_parser

NODES = (np.array([3, 8], np.int64), np.array([3, 8, 11], np.int64))


def _parser():
    parser = argparse.ArgumentParser(prog="jaxsync")
    add_train_parser(parser.add_subparsers(dest="command", required=True))
    return parser


def write_trajectory(path, n_steps=600, dt=0.05, save_every=1, load=None, nodes=NODES):
    """Distributed-trajectory layout: damped oscillators, one frequency per shared dof."""
    t = np.arange(n_steps) * dt
    with h5py.File(path, "w") as fh:
        fh.attrs.update(n_parts=len(nodes), dt=dt, save_every=save_every)
        if load is not None:
            fh.attrs["load_parameter"] = load
        fh["times"] = t * save_every
        for p, ids in enumerate(nodes):
            freqs = 0.6 + 0.1 * np.arange(3 * ids.size) + 0.05 * p
            w = 2 * np.pi * freqs[None, :]
            disp = (1.0 if load is None else load) * np.exp(-0.02 * w * t[:, None]) * np.cos(w * t[:, None])
            fh[f"parts/{p}/shared_nodes"] = ids
            fh[f"parts/{p}/shared_displacement"] = disp


SMALL = ["--n-s", "2", "--n-past", "6", "--n-future", "5", "--hidden", "6", "--layers", "1", "--batch-size", "8",
         "--eta0", "1e-2", "--gamma", "0.95", "--epochs", "12", "--epochs-per-call", "6", "--no-progress"]


def test_every_option_has_help():
    parser = _parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices["train"]
    for action in sub._actions:
        assert action.help, f"option {action.option_strings or action.dest} has no help text"


def test_train_writes_checkpoint_curves_and_summary(tmp_path):
    # Two runs of one partition with different loads, conditional decoder (q = 3).
    paths = []
    for k, load in enumerate((1.0, 0.6)):
        paths.append(tmp_path / f"run{k}.h5")
        write_trajectory(paths[-1], load=load)
    out = tmp_path / "out"
    args = _parser().parse_args(["train", *map(str, paths), "-o", str(out), "--cond-repeat", "3",
                                 "--emse-applications", "20", *SMALL])
    assert args.func(args) == 0

    ckpt = load_checkpoint(out / "surrogate.h5")
    check_compatible(ckpt, NODES)
    assert ckpt.dof_counts == (6, 9) and ckpt.arch.n_dof == 9 and ckpt.n_s == 2
    assert ckpt.arch.n_hidden == 6 and ckpt.arch.n_past == 6 and ckpt.arch.n_future == 5
    assert ckpt.arch.n_cond_repeat == 3
    assert (out / "loss_curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    summary = json.loads((out / "train_summary.json").read_text())
    assert summary["load_parameters"] == [1.0, 0.6]
    assert summary["dof_counts"] == [6, 9] and summary["training"]["n_epochs_run"] == 12
    assert summary["sampling"]["n_train_windows"] + summary["sampling"]["n_val_windows"] == 2 * (150 - 11 + 1)
    assert len(summary["loss_history"]["val"]) == 12 and len(summary["loss_history"]["val"][0]) == 2
    assert all(f < i for f, i in zip(summary["final_val_loss"], summary["initial_val_loss"]))
    assert summary["e_mse_applications"] == 20 and len(summary["sqrt_e_mse"]) == 2
    assert all(np.isfinite(summary["sqrt_e_mse"]))
    assert summary["seconds_per_epoch"] > 0 and summary["gradient_steps_per_second"] > 0
    assert ckpt.metadata["final_val_loss"] == summary["final_val_loss"]
    assert not [p.name for p in out.iterdir() if ".tmp" in p.name]


def test_train_errors(tmp_path):
    sparse = tmp_path / "every5.h5"
    write_trajectory(sparse, save_every=5)
    args = _parser().parse_args(["train", str(sparse), "-o", str(tmp_path / "x"), *SMALL])
    with pytest.raises(CheckpointError, match="save_every=1"):
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
