"""The surrogate API's settings: frozen dataclasses that keep the library's defaults and
refuse bad values (the parameter-count and signature checks: tests/test_structure.py)."""

import dataclasses
import pathlib

import pytest

from jaxsync.errors import ConfigError
from jaxsync.surrogate import (
    ArchitectureChoice,
    LinearFitConfig,
    LSTMArchitecture,
    Sampling,
    TrainConfig,
    TrainingChecks,
    TrainingState,
)


def test_the_settings_keep_the_library_defaults():
    arch, sampling, config, checks = ArchitectureChoice(), Sampling(), TrainConfig(), TrainingChecks()
    lstm = arch.lstm(7, sampling.n_past, sampling.n_future)
    assert lstm == LSTMArchitecture(n_dof=7, highway=True)  # n_H 50, k 2, n_p = n_f = 20, q 0, float32
    assert not dataclasses.replace(arch, n_cond_repeat=12).lstm(7, 20, 20).highway  # the conditional network
    assert arch.model == "lstm" and arch.fit_config == LinearFitConfig()
    assert (sampling.n_s, sampling.train_fraction, sampling.val_fraction, sampling.n_offsets, sampling.split,
            sampling.load_jump_windows, sampling.seed) == (150, 0.5, 0.25, 1, "interleaved", None, 0)
    assert (config.batch_size, config.n_epochs, config.patience, config.n_candidates) == (10, 800, 200, 2)
    assert (checks.emse_applications, checks.rollout_tolerance) == (60, 0.02)
    assert TrainingState("out").every == 50 and TrainingState("out").path == str(pathlib.Path("out",
                                                                                             "training_state.h5"))
    for settings in (arch, sampling, config, checks, TrainingState("out")):
        with pytest.raises(dataclasses.FrozenInstanceError):
            settings.seed = 1


def test_load_jump_windows_follow_the_model_unless_given():
    assert Sampling().for_model("lstm").load_jump_windows == "keep"
    assert Sampling().for_model("linear").load_jump_windows == "exclude"
    assert Sampling(load_jump_windows="keep").for_model("linear").load_jump_windows == "keep"


@pytest.mark.parametrize("make, match", [
    (lambda: ArchitectureChoice(model="gru"), "model must be one of 'lstm', 'linear'"),
    (lambda: ArchitectureChoice(n_hidden=0), r"ArchitectureChoice.n_hidden must be an integer >= 1"),
    (lambda: ArchitectureChoice(n_cond_repeat=-1), r"n_cond_repeat must be an integer >= 0"),
    (lambda: ArchitectureChoice(dtype="float16"), r"dtype must be 'float32' or 'float64'"),
    (lambda: ArchitectureChoice(model="linear", n_cond_repeat=2), "unconditional.*--model lstm"),
    (lambda: ArchitectureChoice(regularization=float("nan")), "regularization must be a finite number"),
    (lambda: Sampling(n_s=0), r"Sampling.n_s must be an integer >= 1"),
    (lambda: Sampling(n_past=2.5), r"Sampling.n_past must be an integer"),
    (lambda: Sampling(train_fraction=0.0), r"train fraction n_ts must be in \(0, 1\]"),
    (lambda: Sampling(val_fraction=1.0), r"validation fraction must be in \(0, 1\)"),
    (lambda: Sampling(n_s=4, n_offsets=5), "n_offsets must be an integer from 1 to n_s=4"),
    (lambda: Sampling(split="every"), "split must be one of 'interleaved', 'random'"),
    (lambda: Sampling(load_jump_windows="drop"), "load_jump_windows must be one of 'exclude', 'keep'"),
    (lambda: Sampling(seed=-1), "Sampling.seed must be an integer >= 0"),
    (lambda: TrainConfig(n_candidates=0), r"n_candidates must be an integer >= 1"),
    (lambda: TrainingChecks(emse_applications=-1), "emse_applications must be an integer >= 0"),
    (lambda: TrainingChecks(rollout_tolerance=0.0), "rollout_tolerance must be > 0"),
    (lambda: TrainingState("out", every=0), "TrainingState.every must be an integer >= 1.*state=None"),
    (lambda: TrainingState(None), "TrainingState.folder must be a folder path"),
])
def test_bad_settings_are_refused_where_they_are_made(make, match):
    with pytest.raises(ConfigError, match=match):
        make()


def test_settings_of_the_wrong_kind_are_refused_by_name(tmp_path):
    from jaxsync.surrogate import train_surrogates

    with pytest.raises(ConfigError, match="sampling must be a jaxsync.surrogate.Sampling"):
        train_surrogates(tmp_path / "run.h5", sampling={"n_s": 2})
    with pytest.raises(ConfigError, match=r"state must be a jaxsync.surrogate.TrainingState\(folder, every\)"):
        train_surrogates(tmp_path / "run.h5", state=str(tmp_path))
