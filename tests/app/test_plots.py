"""Report figures and summary (jaxsync.app.plots, jaxsync.app.figures, jaxsync report):
which nodes are monitored, readable figures, summary entries."""

import dataclasses
import json

import numpy as np
import pytest

import jaxsync
from jaxsync.app import figures, plots
from jaxsync.cli import main
from jaxsync.errors import ConfigError, ProblemError
from jaxsync.io.trajectory import PartHistory

N_STEPS, SAVE_EVERY = 4000, 10  # 1 s of physical time: the beam bends, the load is ramped


def vessel_like():
    """A box beam clamped at both ends (a straight 'vessel'): the old geometric tip,
    the corner at the largest x, is clamped."""
    mesh = jaxsync.box_beam()
    clamps = tuple(jaxsync.Dirichlet(where=lambda p, x=x: np.abs(p[:, 0] - x) < 1e-9) for x in (0.0, 25.0))
    return jaxsync.Problem(mesh=mesh, material=jaxsync.LinearElastic(1.0e6, 0.3, 1.0), dirichlet=clamps,
                           loads=(jaxsync.BodyForce((0.0, 0.0, -0.5), jaxsync.Ramp(1.0)),), damping=0.5)


def fake_online(reference, partition, resync=((200, 240), (320, 330)), n_cri_snapshot=40, seed=0):
    """A synchronization-avoiding trajectory made from the reference: exact while
    synchronized, perturbed while predicted, with per-part predictions at shared nodes."""
    d = np.asarray(reference.displacement)
    T = len(d)
    sync = np.zeros(T, bool)
    sync[:n_cri_snapshot + 1] = True
    for a, b in resync:
        sync[a:b] = True
    amp = np.abs(d).max()
    ramp = np.linspace(0.0, 1.0, d.shape[1])[None, :, None]
    pert = 0.03 * amp * np.sin(np.linspace(0.0, 20.0, T))[:, None, None] * ramp
    pred = np.where(sync[:, None, None], d, d + pert)
    rng = np.random.default_rng(seed)
    parts = []
    for part in partition.parts:
        sh = part.shared_nodes
        own = pred[~sync][:, sh] + 1e-3 * amp * rng.standard_normal((int((~sync).sum()), len(sh), 3))
        parts.append(PartHistory(sh, part.elements, pred[:, sh].reshape(T, -1),
                                 own.reshape(len(own), -1)))
    return dataclasses.replace(reference, displacement=pred, synchronized=sync, parts=tuple(parts),
                               parameters={**reference.parameters, "n_cri": n_cri_snapshot * SAVE_EVERY})


@pytest.fixture(scope="module")
def cantilever_case():
    problem = jaxsync.cantilever()
    reference = jaxsync.simulate(problem, N_STEPS, save=SAVE_EVERY)
    parts = jaxsync.partition(problem.mesh, 2)
    return problem, reference, parts, fake_online(reference, parts)


@pytest.fixture(scope="module")
def vessel_case():
    problem = vessel_like()
    reference = jaxsync.simulate(problem, N_STEPS, save=SAVE_EVERY)
    parts = jaxsync.partition(problem.mesh, 2)
    return problem, reference, parts, fake_online(reference, parts)


def dirichlet_nodes(problem):
    return np.unique(problem.dirichlet_dofs()[0] // 3)


def test_vessel_default_nodes_are_never_constrained(vessel_case, tmp_path):
    problem, reference, parts, online = vessel_case
    clamped = dirichlet_nodes(problem)
    assert plots.tip_node(problem.mesh) in clamped  # the old choice: a clamped node, error 0.0
    summary = plots.write_report(reference, online, parts, tmp_path, fixed_nodes=clamped)
    chosen = np.array(list(summary["nodes"].values()))
    assert not np.isin(chosen, clamped).any()
    # one node per part (not shared) and one shared node, each the largest amplitude there
    amp = np.abs(np.asarray(reference.displacement)[:, :, 2]).max(axis=0)
    shared = set(parts.shared_nodes.tolist())
    for part in parts.parts:
        node = summary["nodes"][f"part {part.index}, largest amplitude"]
        assert node in part.nodes and node not in shared
        others = [n for n in part.nodes if n not in shared and n not in clamped]
        assert amp[node] == pytest.approx(max(amp[others]))
    node = summary["nodes"]["shared, largest amplitude"]
    assert node in shared and amp[node] == pytest.approx(max(amp[sorted(shared - set(clamped))]))
    # the headline entries describe a moving node, not a clamp
    assert summary["tip_max_abs_displacement"] > 0 and summary["tip_max_abs_error"] > 0
    x = problem.mesh.points[summary["monitored_node"], 0]
    assert 5.0 < x < 20.0  # mid-span of a beam clamped at both ends
    assert summary["tip_max_abs_displacement"] == pytest.approx(amp[chosen].max())
    # without fixed_nodes the clamps are still left out: they never move
    again = plots.write_report(reference, online, parts, tmp_path / "again")
    assert again["nodes"] == summary["nodes"]
    # summary.json holds the per-node table
    written = json.loads((tmp_path / "summary.json").read_text())
    table = {row["node"]: row for row in written["node_errors"]}
    assert set(table) == set(chosen.tolist())
    for row in table.values():
        assert not row["constrained"] and row["max_abs_displacement"] > 0
        # the z errors of the node against the trajectories themselves (numpy, not the report)
        z_ref = np.asarray(reference.displacement)[:, row["node"], 2]
        z_err = np.abs(np.asarray(online.displacement)[:, row["node"], 2] - z_ref)
        assert row["max_abs_error"] == pytest.approx(z_err.max(), rel=1e-12)
        assert row["relative_max_error"] == pytest.approx(z_err.max() / np.abs(z_ref).max(), rel=1e-12)
    assert written["monitored_node"] == summary["monitored_node"]


def test_cantilever_default_monitors_the_free_end(cantilever_case, tmp_path):
    problem, reference, parts, online = cantilever_case
    summary = plots.write_report(reference, online, parts, tmp_path, fixed_nodes=dirichlet_nodes(problem))
    coords = problem.mesh.points[list(summary["nodes"].values())]
    assert np.isclose(coords[:, 0], 25.0).any()
    assert problem.mesh.points[summary["monitored_node"], 0] == pytest.approx(25.0)
    ref = np.asarray(reference.displacement)
    node = summary["monitored_node"]
    assert summary["tip_max_abs_displacement"] == pytest.approx(np.abs(ref[:, node, 2]).max())
    err = np.abs(np.asarray(online.displacement)[:, node, 2] - ref[:, node, 2]).max()
    assert summary["tip_max_abs_error"] == pytest.approx(err) and err > 0
    assert summary["node_notes"] == []


def test_user_nodes_by_id_and_coordinates(cantilever_case, tmp_path):
    problem, reference, parts, online = cantilever_case
    points = problem.mesh.points
    corner = int(np.argmin(np.linalg.norm(points - [25.0, 1.0, 1.0], axis=1)))
    summary = plots.write_report(reference, online, parts, tmp_path, nodes=[12, (25.0, 1.0, 1.0)])
    assert summary["nodes"] == {"node 12": 12, "nearest to (25, 1, 1)": corner}
    assert [row["node"] for row in summary["node_errors"]] == [12, corner]
    labelled = plots.write_report(reference, online, parts, tmp_path / "l",
                                  nodes={"mid": (12.4, 0.1, 0.0), "clamp": 0})
    assert labelled["nodes"]["mid"] == int(np.argmin(np.linalg.norm(points - [12.4, 0.1, 0.0], axis=1)))
    assert labelled["nodes"]["clamp"] == 0  # a named node is honoured, even a constrained one
    with pytest.raises(ConfigError, match="node 104 does not exist.*0 .. 103"):
        plots.write_report(reference, online, parts, tmp_path / "bad", nodes=[104])
    with pytest.raises(ConfigError, match="node id .*coordinates"):
        plots.write_report(reference, online, parts, tmp_path / "bad", nodes=[(1.0, 2.0)])
    # off the body: farther from every node than the longest element edge (sqrt(3) cm on this beam)
    with pytest.raises(ConfigError, match=r"node \(100, 100, 100\) is off the mesh.*bounding box is \(0, 0, 0\) to"):
        plots.write_report(reference, online, parts, tmp_path / "bad", nodes=[(100.0, 100.0, 100.0)])
    assert plots.resolve_nodes(problem.mesh, [(26.5, 1.0, 1.0)]) == {"nearest to (26.5, 1, 1)": corner}
    assert plots.parse_node("12") == 12 and plots.parse_node("25,1,1") == (25.0, 1.0, 1.0)
    with pytest.raises(ConfigError, match="--node 25,1,1"):
        plots.parse_node("tip")


def test_no_candidate_is_said_clearly(cantilever_case, tmp_path):
    problem, reference, parts, online = cantilever_case
    everything = np.arange(problem.mesh.n_nodes)
    with pytest.raises(ProblemError, match="no node to monitor.*--node"):
        plots.write_report(reference, online, parts, tmp_path, fixed_nodes=everything)
    shared = set(parts.shared_nodes.tolist())
    part0_inner = [n for n in parts.parts[0].nodes if n not in shared]
    summary = plots.write_report(reference, online, parts, tmp_path,
                                 fixed_nodes=np.union1d(part0_inner, dirichlet_nodes(problem)))
    assert "part 0, largest amplitude" not in summary["nodes"]
    assert any(note.startswith("part 0:") for note in summary["node_notes"])


def test_phases_and_histogram_bins():
    times = np.arange(10) * 0.1
    flags = np.array([1, 1, 0, 0, 1, 1, 0, 0, 0, 1], bool)
    t_switch, spans = figures.phases(times, flags)
    assert t_switch == pytest.approx(0.1)
    assert spans == [pytest.approx((0.35, 0.55)), pytest.approx((0.85, 0.9))]
    assert figures.phases(times, np.ones(10, bool)) == (None, [])
    few = figures.histogram_bins([1e-3, 2e-3, 3e-3, 4e-3])
    assert 3 <= len(few) - 1 <= 5 and few[0] <= 1e-3 and few[-1] >= 4e-3
    wide = figures.histogram_bins(np.geomspace(1e-6, 1e-2, 400))
    assert len(wide) - 1 == 20 and np.allclose(np.diff(np.log(wide)), np.log(wide[1] / wide[0]))
    same = figures.histogram_bins([2e-4] * 3)
    assert same[0] < 2e-4 < same[-1] and same[-1] - same[0] < 1e-4


def test_every_figure_is_labelled(cantilever_case, tmp_path):
    problem, reference, parts, online = cantilever_case
    fixed = dirichlet_nodes(problem)
    names = {"displacement_nodes.png", "l2_error.png", "shared_errors.png", "et_histogram.png", "es_tracking.png"}
    plots.write_report(reference, online, parts, tmp_path, fixed_nodes=fixed)
    assert {path.name for path in tmp_path.glob("*.png")} == names
    for name in names:
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the figures write_report saved, drawn again from the same comparison
    drawn = plots.report_figures(plots.compare(reference, online, parts, fixed_nodes=fixed))
    assert set(drawn) == names
    for name, fig in drawn.items():
        fig.canvas.draw()
        titled = bool(fig.get_suptitle()) or all(ax.get_title() for ax in fig.axes)
        assert titled, name
        assert fig.legends or all(ax.get_legend() for ax in fig.axes), name
        for ax in fig.axes:  # units everywhere, except on a count of nodes
            assert ax.get_ylabel() and ("[" in ax.get_ylabel() or name == "et_histogram.png"), name
        assert any("[" in ax.get_xlabel() for ax in fig.axes), name
        if name not in ("et_histogram.png", "es_tracking.png"):  # time plots: both phases in the legend
            labels = [t.get_text() for legend in fig.legends for t in legend.get_texts()]
            assert any("end of synchronized phase" in t for t in labels), name
            assert "re-synchronized" in labels, name
            spans = [p for p in fig.axes[0].patches if p.get_label() == "re-synchronized"]
            assert len(spans) == 1  # one legend entry; the other span is unlabelled
            assert len(fig.axes[0].patches) == 2
    tracking = drawn["es_tracking.png"].axes[0]
    assert tracking.get_xscale() == tracking.get_yscale() == "log"
    hist = drawn["et_histogram.png"].axes[0]
    assert hist.get_ylabel() == "number of shared nodes"
    ticks = hist.get_yticks()
    assert np.allclose(ticks, np.round(ticks))  # counts of nodes: integer ticks
    nodes_fig = drawn["displacement_nodes.png"]
    assert len(nodes_fig.axes) == 2 * 3  # a displacement and an error panel per node
    lines = {line.get_label(): line for line in nodes_fig.axes[0].get_lines()}
    ref_line = lines["synchronized (reference)"]
    pred_line = lines["synchronization-avoiding (predicted)"]
    # the reference is drawn wide and underneath, the prediction thin on top, other colours
    assert ref_line.get_linewidth() > 2 * pred_line.get_linewidth()
    assert ref_line.get_zorder() < pred_line.get_zorder() and ref_line.get_color() != pred_line.get_color()
    assert any("error" in line.get_label() for line in nodes_fig.axes[1].get_lines())


VESSEL_TOML = ('[problem]\nkind = "general"\n'
               '[[dirichlet]]\nplane = { axis = 0, value = 0.0 }\n'
               '[[dirichlet]]\nplane = { axis = 0, value = 25.0 }\n'
               '[[body_force]]\nvector = [0.0, 0.0, -0.5]\nt_ramp = 1.0\n')


def test_constrained_nodes_from_a_config(tmp_path):
    problem = vessel_like()
    rng = np.random.default_rng(1)
    moving = rng.standard_normal((3, problem.mesh.n_nodes, 3))  # every node moves
    moving[:, 7] = 0.25  # ... but this one, which never moves
    clamped = dirichlet_nodes(problem)
    cfg = tmp_path / "vessel.toml"
    cfg.write_text(VESSEL_TOML)
    np.testing.assert_array_equal(plots.constrained_nodes(str(cfg), problem.mesh, moving),
                                  np.union1d(clamped, [7]))
    # without a configuration: the nodes that never move, nothing assumed
    assert plots.constrained_nodes(None, problem.mesh, moving).tolist() == [7]
    # a configuration made for another mesh is applied to this one ...
    longer = tmp_path / "longer.toml"
    longer.write_text('[mesh]\nlength = 40.0\ndivisions = [40, 1, 1]\n' + VESSEL_TOML)
    np.testing.assert_array_equal(plots.constrained_nodes(str(longer), problem.mesh, moving),
                                  np.union1d(clamped, [7]))
    # ... and a condition that selects nothing there is an error
    far = tmp_path / "far.toml"
    far.write_text('[mesh]\nlength = 40.0\ndivisions = [40, 1, 1]\n[problem]\nkind = "general"\n'
                   '[[dirichlet]]\nplane = { axis = 0, value = 40.0 }\n')
    with pytest.raises(ConfigError, match="selects no node"):
        plots.constrained_nodes(str(far), problem.mesh, moving)


def test_report_command_on_a_vessel(vessel_case, tmp_path, capsys):
    problem, reference, parts, online = vessel_case
    reference.save(tmp_path / "sync.h5")
    online.save(tmp_path / "online.h5")
    (tmp_path / "vessel.toml").write_text(VESSEL_TOML)
    for config in ([], ["--config", str(tmp_path / "vessel.toml")]):
        out = tmp_path / f"r{len(config)}"
        assert main(["report", str(tmp_path / "sync.h5"), str(tmp_path / "online.h5"),
                     "-o", str(out), *config]) == 0
        assert "largest-amplitude monitored node" in capsys.readouterr().out
        summary = json.loads((out / "summary.json").read_text())
        assert not np.isin(list(summary["nodes"].values()), dirichlet_nodes(problem)).any()
        assert summary["tip_max_abs_error"] > 0 and len(summary["nodes"]) == 3
        for name in ("displacement_nodes.png", "l2_error.png", "shared_errors.png", "et_histogram.png"):
            assert (out / name).stat().st_size > 1000

    assert main(["report", str(tmp_path / "sync.h5"), str(tmp_path / "online.h5"), "-o", str(tmp_path / "n"),
                 "--node", "12", "--node", "25,1,1", "--component", "1"]) == 0
    summary = json.loads((tmp_path / "n" / "summary.json").read_text())
    corner = int(np.argmin(np.linalg.norm(problem.mesh.points - [25.0, 1.0, 1.0], axis=1)))
    assert summary["nodes"] == {"node 12": 12, "nearest to (25, 1, 1)": corner} and summary["component"] == "y"

    capsys.readouterr()
    assert main(["report", str(tmp_path / "sync.h5"), str(tmp_path / "online.h5"), "-o", str(tmp_path / "e"),
                 "--node", "9999"]) == 2
    assert "node 9999 does not exist" in capsys.readouterr().err


def test_report_when_the_parts_predictions_agree_exactly(cantilever_case, tmp_path, capsys):
    """es_hat = 0 at every snapshot (two parts whose identical linear fits agree: the README
    pipeline with --model linear): one line that says its tracking cannot be measured, no
    numpy warning, and a summary.json without NaN/Infinity (null instead)."""
    _, reference, parts, online = cantilever_case
    same = tuple(dataclasses.replace(p, predicted_shared_displacement=np.asarray(
        online.displacement)[~online.synchronized][:, p.shared_nodes].reshape(-1, 3 * len(p.shared_nodes)))
        for p in online.parts)
    reference.save(tmp_path / "sync.h5")
    dataclasses.replace(online, parts=same).save(tmp_path / "online.h5")
    capsys.readouterr()
    assert main(["report", str(tmp_path / "sync.h5"), str(tmp_path / "online.h5"), "-o", str(tmp_path / "r")]) == 0
    out, err = capsys.readouterr()
    assert "warning" not in err.lower(), err
    assert "es_hat is 0 at every one of the" in out and "its tracking of es cannot be measured" in out
    assert "inf" not in out and "nan" not in out

    def refuse(token):
        raise AssertionError(f"summary.json holds {token}")

    summary = json.loads((tmp_path / "r" / "summary.json").read_text(), parse_constant=refuse)
    tracking = summary["es_hat_tracking"]
    assert tracking["ratio_median"] is None and tracking["log_correlation"] is None and tracking["underestimated"] == 1
    assert summary["es_hat_max"] == 0.0 and summary["es_max"] > 0
