"""The exchange protocol (jaxsync.parallel.ExchangeStrategy): an exchange written here,
through the public protocol only (an all-gather and sum over the devices, the worked
example of docs/guides/extending-exchanges.md), runs everything a built-in exchange runs,
compared with the built-in jaxsync.Psum and the single-device run; the registry of names;
and no module of the package switching on an exchange's class or name."""

import dataclasses
import pathlib
import re

import jax
import numpy as np
import pytest

import jaxsync
from jaxsync.parallel import AXIS, xla_devices, xla_plan
from jaxsync.solve import register_exchange, sync_strategy, unregister_exchange
from jaxsync.solve.coupling import OraclePredictor
from jaxsync.surrogate.training import shared_dof_layout

ROOT = pathlib.Path(__file__).resolve().parents[2]
GUIDE = ROOT / "docs" / "guides" / "extending-exchanges.md"

# ---- the guide's first code block, verbatim (test_the_guide_shows_this_exchange) ----


def gather_and_sum(total):
    """(n_interface + 1, c) interface values summed over this device's parts -> the same
    summed over all devices: every device gathers all devices' vectors and adds them."""
    return jax.lax.all_gather(total, AXIS).sum(axis=0)


@dataclasses.dataclass(frozen=True)
class GatherSum:
    """The parts' shared-node forces summed by an all-gather over the devices every step.

    Attributes:
        devices: the devices of the run (default: as many of jax.devices() as divide the
            part count).
    """

    devices: tuple | None = None

    name = "gather-sum"
    synchronizes_every_step = True

    def plan(self, partition, devices=None):
        devices = xla_devices(partition.n_parts, self.devices if devices is None else devices)
        # an all-gather moves every device's whole interface vector to every other device:
        # priced as a ring (p - 1 steps), with the ring reduce-scatter's steps on top
        return xla_plan(partition, devices, gather_and_sum, algorithm="allreduce-ring")

    def transport(self, n_parts=None):
        return f"XLA all-gather and sum over {len(xla_devices(n_parts or 1, self.devices))} devices"

# ---- end of the guide's code block ----


N_STEPS, SAVE = 600, 10


@pytest.fixture(scope="module")
def problem():
    return jaxsync.cantilever()


@pytest.fixture(scope="module")
def partition(problem):
    return jaxsync.partition(problem.mesh, 2, seed=0)


@pytest.fixture(scope="module")
def single(problem):
    return jaxsync.simulate(problem, N_STEPS, save=SAVE)


@pytest.fixture(scope="module")
def psum(problem, partition):
    return jaxsync.simulate(problem, N_STEPS, save=SAVE, partitions=partition, sync=jaxsync.Psum())


def close(a, b, reference):
    """|a - b| within round-off of the reference run's largest displacement."""
    return np.abs(np.asarray(a) - np.asarray(b)).max() <= 1e-12 * np.abs(reference.displacement).max()


def test_the_guide_shows_this_exchange():
    blocks = re.findall(r"```python\n(.*?)```", GUIDE.read_text(), flags=re.S)
    assert blocks, "the guide has no python code block"
    source = pathlib.Path(__file__).read_text()
    # its imports are this file's, and its code from the first definition on is this file's
    imports = [line for line in blocks[0].splitlines() if line.startswith(("import ", "from "))]
    assert imports and all(f"\n{line}\n" in source for line in imports)
    assert blocks[0][blocks[0].index("\ndef "):].strip() in source
    # and the guide's block runs by itself, giving an exchange of the protocol
    namespace = {}
    exec(compile(blocks[0], str(GUIDE), "exec"), namespace)  # noqa: S102 - the documented example
    assert isinstance(namespace["GatherSum"](), jaxsync.parallel.ExchangeStrategy)


def test_a_user_exchange_equals_psum_and_the_single_device_run(problem, partition, single, psum):
    run = jaxsync.simulate(problem, N_STEPS, save=SAVE, partitions=partition, sync=GatherSum(),
                           executor=jaxsync.HostExecutor(progress=False))
    assert len(jax.devices()) == 2 and len(run.parts) == 2
    assert close(run.displacement, psum.displacement, single)
    assert close(run.displacement, single.displacement, single)
    assert np.abs(single.displacement).max() > 0  # a run that moves


def test_the_compiled_step_runs_the_user_exchange(problem, partition):
    """The step holds the exchange's all-gather (and the psum run's does not): the run
    above went through GatherSum.plan, not a built-in default."""
    from jaxsync.fem import build_system, initial_state
    from jaxsync.solve.executors import DistributedRunner

    system = build_system(problem, problem.dt)
    texts = {}
    for sync in (GatherSum(), jaxsync.Psum()):
        runner = DistributedRunner(problem, system, partition, save_every=1, sync=sync)
        state = runner.from_global(initial_state(problem, system))
        texts[sync.name] = runner._compiled(1).lower(runner.parts, state).compile().as_text().lower()
    assert "all-gather" in texts["gather-sum"] and "all-gather" not in texts["psum"]


def test_the_traced_executor_runs_the_user_exchange(problem, partition, psum, single):
    run = jaxsync.simulate(problem, N_STEPS, save=SAVE, partitions=partition, sync=GatherSum(),
                           executor=jaxsync.TracedExecutor())
    assert close(run.displacement, psum.displacement, single)


def test_gradients_flow_through_the_user_exchange(problem, partition):
    """d(displacement)/d(E, damping) through the user exchange equals the psum run's."""
    def loss(**kwargs):
        def value(E, alpha):
            p = problem.replace(material=jaxsync.LinearElastic(E, 0.3, 1.0), damping=alpha)
            return jaxsync.simulate(p, 50, dt=problem.dt, save=50, **kwargs).displacement[-1, :, 2].sum()
        return jax.jit(jax.grad(value, (0, 1)))  # one program each

    args = (1.0e6, 0.5)
    ours = loss(partitions=partition, sync=GatherSum())(*args)
    theirs = loss(partitions=partition, sync=jaxsync.Psum())(*args)
    for a, b in zip(ours, theirs):
        assert float(b) != 0.0 and float(a) == pytest.approx(float(b), rel=1e-10)


def test_a_checkpointed_run_with_the_user_exchange_resumes(problem, partition, psum, single, tmp_path):
    ckpt = tmp_path / "c.h5"
    executor = jaxsync.HostExecutor(chunk_steps=200, progress=False)
    jaxsync.simulate(problem, 200, save=SAVE, partitions=partition, sync=GatherSum(), executor=executor,
                     checkpoint=ckpt)
    resumed = jaxsync.simulate(problem, N_STEPS, save=SAVE, partitions=partition, sync=GatherSum(),
                               executor=executor, checkpoint=ckpt)
    uninterrupted = jaxsync.simulate(problem, N_STEPS, save=SAVE, partitions=partition, sync=GatherSum(),
                                     executor=executor)
    np.testing.assert_array_equal(resumed.displacement, uninterrupted.displacement)
    assert close(resumed.displacement, psum.displacement, single)


def test_a_sync_avoiding_run_with_the_user_exchange(problem, partition):
    """The synchronization-avoiding solver with an oracle of the synchronized run: its
    synchronized stretch and its error probes go through the user exchange, and the run
    equals the same run with Psum and the synchronized run to round-off."""
    n_s, n_p, n_f = 5, 4, 4
    n_cri = n_s * n_p + 20
    n_steps = n_cri + 2 * n_s * n_f
    reference = jaxsync.simulate(problem, n_steps, partitions=partition)
    n_dof, counts = shared_dof_layout(partition)
    future = np.zeros((2, n_steps - n_cri, n_dof))
    for p, part in enumerate(partition.parts):
        future[p, :, :counts[p]] = reference.displacement[n_cri + 1:, part.shared_nodes].reshape(n_steps - n_cri, -1)
    oracle = OraclePredictor(future, first_step=n_cri + 1, n_s=n_s, n_past=n_p, n_future=n_f)
    runs = {sync.name: jaxsync.simulate_sync_avoiding(problem, n_steps, partitions=partition, surrogates=oracle,
                                                      n_cri=n_cri, sync=sync, resync_tolerance="1%")
            for sync in (GatherSum(), jaxsync.Psum())}
    assert runs["gather-sum"].synchronized.sum() == n_cri + 1
    assert close(runs["gather-sum"].displacement, runs["psum"].displacement, reference)
    assert close(runs["gather-sum"].displacement, reference.displacement, reference)


def test_the_plan_holds_layout_exchange_and_cost(partition):
    plan = GatherSum().plan(partition)
    assert plan.parts is partition and plan.layout.n_parts == 2 and len(plan.devices) == 2
    assert plan.halo_depth is None and plan.exchange.n_interface == partition.n_interface
    # the cost: the interface in float64 forces, every step, priced as a ring allreduce
    assert plan.cost.every == 1 and plan.cost.bytes_per_exchange == 3 * 8 * partition.n_interface
    link = jaxsync.perf.costmodel.Interconnect("test", latency_s=1e-6, bandwidth_Bps=1e9)
    size = 3 * 8 * partition.n_interface
    assert plan.cost.time_per_step(link) == pytest.approx(2 * (2 - 1) * (1e-6 + size / 2 / 1e9))
    # deep halos: the grown parts, both displacement levels every k steps
    halo = jaxsync.Halo(4).plan(partition)
    assert halo.halo_depth == 4 and halo.cost.every == 4 and halo.cost.pattern.dofs_per_node == 6
    assert halo.parts.n_interface == halo.exchange.n_interface and halo.parts.redundancy() > 1
    assert halo.cost.time_per_step(link) == pytest.approx(halo.cost.time_per_exchange(link) / 4)


def test_registration_names_the_exchange(problem, partition, psum, single):
    from jaxsync.cli import build_parser

    with pytest.raises(jaxsync.ConfigError, match="must be one of 'psum', 'ppermute', 'mpi', 'halo', got 'gather-sum'"):
        sync_strategy("gather-sum")
    register_exchange("gather-sum", GatherSum)
    try:
        assert sync_strategy("gather-sum") == GatherSum()
        assert "gather-sum" in jaxsync.solve.exchange_names()
        run = jaxsync.simulate(problem, N_STEPS, save=SAVE, partitions=partition, sync="gather-sum")
        assert close(run.displacement, psum.displacement, single)
        assert jaxsync.solve.transport("gather-sum", 2) == "XLA all-gather and sum over 2 devices"
        # the command line offers it (jaxsync simulate and jaxsync predict: it synchronizes every step)
        parser = build_parser()
        for command in ("simulate", "predict"):
            sub = parser._subparsers._group_actions[0].choices[command]
            sync_option = next(a for a in sub._actions if "--sync" in a.option_strings)
            assert "gather-sum" in sync_option.choices
        # an unknown name lists the registered ones, the user's too
        with pytest.raises(jaxsync.ConfigError, match="'halo', 'gather-sum', got 'allgather'"):
            sync_strategy("allgather")
        with pytest.raises(jaxsync.ConfigError, match="already registered"):
            register_exchange("gather-sum", lambda: GatherSum())
    finally:
        unregister_exchange("gather-sum")
    assert "gather-sum" not in jaxsync.solve.exchange_names()


def test_the_built_in_names_and_their_arguments():
    assert sync_strategy("psum") == jaxsync.Psum() and sync_strategy("ppermute") == jaxsync.Ppermute()
    assert sync_strategy("halo") == jaxsync.Halo(1) and sync_strategy("halo:4") == jaxsync.Halo(4)
    with pytest.raises(jaxsync.ConfigError, match="whole number of steps"):
        sync_strategy("halo:four")
    with pytest.raises(jaxsync.ConfigError, match="not an exchange"):
        sync_strategy(3)
    with pytest.raises(jaxsync.ConfigError, match="built-in"):
        unregister_exchange("psum")
    with pytest.raises(jaxsync.ConfigError, match="letters, digits"):
        register_exchange("two words", GatherSum)


def test_an_exchange_is_known_by_its_behaviour_not_its_label(problem, partition, psum, single):
    """An exchange labelled like a built-in one runs as what it is: labelled 'halo' (deep
    halos cannot record every step) it records every step; labelled 'mpi' it runs over
    the devices of one process."""
    for label in ("halo", "mpi", "ppermute"):
        mislabelled = dataclasses.make_dataclass(f"Labelled{label}", [], bases=(GatherSum,), frozen=True,
                                                 namespace={"name": label})()
        run = jaxsync.simulate(problem, N_STEPS, save=jaxsync.SaveAt(every=SAVE, shared_every=1),
                               partitions=partition, sync=mislabelled)
        assert close(run.displacement, psum.displacement, single)
        nodes = partition.parts[0].shared_nodes
        assert run.parts[0].shared_displacement.shape == (N_STEPS + 1, 3 * len(nodes))
        assert jaxsync.solve.transport(mislabelled, 2) == "XLA all-gather and sum over 2 devices"


def test_no_module_switches_on_an_exchange_class_or_name():
    """The package reads the exchange's plan: no isinstance test on an exchange class and
    no comparison of an exchange's name anywhere in jaxsync."""
    classes = r"\b(Psum|Ppermute|Mpi|Halo)\b"
    patterns = [re.compile(r"isinstance\([^)]*" + classes),  # isinstance(x, Halo), isinstance(x, (Psum, ...))
                re.compile(r"\.name\s*(==|!=|in\b)\s*[\"'(]?(psum|ppermute|mpi|halo)"),
                re.compile(r"[\"'](psum|ppermute|mpi|halo)[\"']\s*(==|!=)\s*\w*\.name\b")]
    found = []
    for path in sorted((ROOT / "jaxsync").rglob("*.py")):
        for number, line in enumerate(path.read_text().splitlines(), 1):
            code = line.split("#")[0]
            if any(p.search(code) for p in patterns):
                found.append(f"{path.relative_to(ROOT)}:{number}: {line.strip()}")
    assert not found, "\n".join(found)


def test_installed_packages_name_exchanges_through_entry_points(monkeypatch):
    """An entry point of the group jaxsync.exchanges is a registered name; one that cannot
    be imported is left out with a warning, and the other names keep working."""
    from importlib.metadata import EntryPoint

    from jaxsync.parallel.exchange import ENTRY_POINT_GROUP, EntryPointWarning

    points = [EntryPoint("psum-from-a-package", "jaxsync.parallel.exchange:Psum", ENTRY_POINT_GROUP),
              EntryPoint("broken-package", "no_such_module_for_jaxsync:Thing", ENTRY_POINT_GROUP)]
    monkeypatch.setattr("importlib.metadata.entry_points",
                        lambda group: [p for p in points if p.group == group])
    monkeypatch.setattr("jaxsync.parallel.exchange._builtin._ENTRY_POINTS_READ", [])  # read the entry points again
    try:
        with pytest.warns(EntryPointWarning, match="broken-package.*no_such_module_for_jaxsync"):
            assert sync_strategy("psum-from-a-package") == jaxsync.Psum()
        assert "broken-package" not in jaxsync.solve.exchange_names()
        assert sync_strategy("halo:2") == jaxsync.Halo(2)
    finally:
        unregister_exchange("psum-from-a-package")


def test_an_exchange_that_does_not_synchronize_every_step_records_nothing(problem, partition):
    """synchronizes_every_step=False (as deep halos): a run that records every step's
    shared-node history is refused, through both executors, with the fix."""
    periodic = dataclasses.make_dataclass("Periodic", [], bases=(GatherSum,), frozen=True,
                                          namespace={"synchronizes_every_step": False})()
    for executor in (jaxsync.HostExecutor(progress=False), jaxsync.TracedExecutor()):
        with pytest.raises(jaxsync.ConfigError, match="does not synchronize every step.*sync='psum'"):
            jaxsync.simulate(problem, 20, save=jaxsync.SaveAt(every=10, shared_every=1), partitions=partition,
                             sync=periodic, executor=executor)
    # a run that does not record is fine
    jaxsync.simulate(problem, 20, save=10, partitions=partition, sync=periodic)
