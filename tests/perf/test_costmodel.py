"""Communication cost model (jaxsync.perf.costmodel): hand-computed message counts and times,
neighbour patterns checked against the mesh, the latency-bandwidth fit, the projection."""

import json
import math

import numpy as np
import pytest

import jaxsync
from jaxsync import ConfigError, ProblemError
from jaxsync.parallel import partition_from_elements
from jaxsync.perf.costmodel import (
    ALGORITHMS,
    INTERCONNECTS,
    CommunicationPattern,
    Interconnect,
    Projection,
    communication_pattern,
    fit_interconnect,
    project,
    relative_error,
    sync_time,
)

LINK = Interconnect("test", latency_s=1e-6, bandwidth_Bps=1e9, source="hand")


def ring_pattern(p, n_interface):
    """p parts in a ring, each sharing 1 node with the next; only n_parts and n_interface
    matter to the allreduce algorithms."""
    return CommunicationPattern(p, n_interface, tuple(
        tuple((r, 1) for r in sorted({(q - 1) % p, (q + 1) % p})) for q in range(p)))


def test_message_time():
    assert LINK.message_time(1000) == pytest.approx(1e-6 + 1e-6, rel=1e-15)
    assert LINK.message_time(0) == 0.0  # nothing to send
    times = LINK.message_time(np.array([0, 100, 1000]))
    np.testing.assert_allclose(times, [0.0, 1.1e-6, 2e-6], rtol=1e-15)
    with pytest.raises(ProblemError, match="bytes"):
        LINK.message_time(-1)


@pytest.mark.parametrize("p, ring, doubling", [
    # S = 50 nodes * 3 * 8 = 1200 bytes, latency 1 us, 1 GB/s
    (2, 2 * (1e-6 + 600e-9), 1 * (1e-6 + 1200e-9)),
    (3, 4 * (1e-6 + 400e-9), 2 * (1e-6 + 1200e-9)),
    (4, 6 * (1e-6 + 300e-9), 2 * (1e-6 + 1200e-9)),
    (8, 14 * (1e-6 + 150e-9), 3 * (1e-6 + 1200e-9)),
])
def test_allreduce_message_counts(p, ring, doubling):
    pattern = ring_pattern(p, 50)
    assert pattern.interface_bytes == 1200
    assert sync_time(pattern, LINK, "allreduce-ring") == pytest.approx(ring, rel=1e-12)
    assert sync_time(pattern, LINK, "allreduce-recursive-doubling") == pytest.approx(doubling, rel=1e-12)
    assert sync_time(pattern, LINK, "allreduce") == pytest.approx(min(ring, doubling), rel=1e-12)


def test_allreduce_picks_the_cheaper_algorithm_by_size():
    small, large = ring_pattern(4, 50), ring_pattern(4, 50_000)  # 1.2 kB, 1.2 MB
    # short vector: latency dominates, recursive doubling (2 messages) beats ring (6)
    assert sync_time(small, LINK, "allreduce") == pytest.approx(2 * (1e-6 + 1.2e-6))
    # long vector: bandwidth dominates, ring moves 6 * S/4 = 1.5 S, doubling 2 S
    assert sync_time(large, LINK, "allreduce") == pytest.approx(6 * (1e-6 + 300e-6))
    assert sync_time(large, LINK, "allreduce-recursive-doubling") == pytest.approx(2 * (1e-6 + 1.2e-3))


def test_neighbour_exchange_on_a_hand_built_pattern():
    # part 0 shares 10 nodes with part 1 and 5 with part 2; 1 and 2 are not neighbours
    pattern = CommunicationPattern(3, 12, (((1, 10), (2, 5)), ((0, 10),), ((0, 5),)))
    part0 = (1e-6 + 240 / 1e9) + (1e-6 + 120 / 1e9)  # two messages, one after the other
    assert sync_time(pattern, LINK, "neighbour") == pytest.approx(part0, rel=1e-12)
    assert pattern.neighbour_bytes(0) == (240, 120)


def test_shared_memory_collectives_by_hand():
    """One psum call moves S once; the ppermute exchange makes one call per device offset
    at which parts share nodes, each of the largest block at that offset."""
    # chain of 4 parts: offsets +1 (0->1: 10 nodes, 1->2: 4, 2->3: 7) and -1 = 3 (same blocks)
    chain = CommunicationPattern(4, 21, (((1, 10),), ((0, 10), (2, 4)), ((1, 4), (3, 7)), ((2, 7),)))
    assert sync_time(chain, LINK, "collective") == pytest.approx(1e-6 + 21 * 24 / 1e9, rel=1e-12)
    per_offset = 1e-6 + 10 * 24 / 1e9
    assert sync_time(chain, LINK, "collective-permute") == pytest.approx(2 * per_offset, rel=1e-12)
    # parts 0 and 2 also share 3 nodes: offset 2 adds a third call
    wider = CommunicationPattern(4, 22, (((1, 10), (2, 3)), ((0, 10), (2, 4)),
                                         ((0, 3), (1, 4), (3, 7)), ((2, 7),)))
    assert sync_time(wider, LINK, "collective-permute") == pytest.approx(
        2 * per_offset + (1e-6 + 3 * 24 / 1e9), rel=1e-12)


def test_one_part_costs_nothing():
    alone = CommunicationPattern(1, 0, ((),))
    for algorithm in ALGORITHMS:
        assert sync_time(alone, LINK, algorithm) == 0.0
    mesh = jaxsync.box_beam(25.0, 1.0, 1.0, (8, 1, 1))
    pattern = communication_pattern(jaxsync.partition(mesh, 1))
    assert pattern.n_interface == 0 and pattern.neighbours == ((),)
    assert sync_time(pattern, "infiniband-hdr") == 0.0


def part_nodes(mesh, element_part):
    """The set of nodes touched by the elements of each part, from the mesh."""
    return [set(mesh.tets[element_part == p].ravel().tolist()) for p in range(element_part.max() + 1)]


def shared_counts(mesh, element_part):
    """[p, q]: nodes touched by elements of both parts p and q, counted from the mesh."""
    nodes = part_nodes(mesh, element_part)
    return np.array([[len(a & b) for b in nodes] for a in nodes])


def test_pattern_of_a_metis_partition_matches_the_mesh():
    mesh = jaxsync.box_beam(25.0, 1.0, 1.0, (8, 1, 1))
    part = jaxsync.partition(mesh, 2, seed=0)
    counts = shared_counts(mesh, part.element_part)
    pattern = communication_pattern(part)
    assert counts[0, 1] > 0
    assert pattern.n_parts == 2 and pattern.n_interface == counts[0, 1]
    assert pattern.neighbours == (((1, counts[0, 1]),), ((0, counts[0, 1]),))
    # two parts: the neighbour exchange is one message of the whole interface
    assert sync_time(pattern, LINK, "neighbour") == pytest.approx(1e-6 + 24 * counts[0, 1] / 1e9)


def test_pattern_of_a_three_slab_partition():
    # slabs along x: parts 0 and 2 do not touch, 1 touches both
    mesh = jaxsync.box_beam(24.0, 1.0, 1.0, (6, 1, 1))
    x = mesh.points[mesh.tets].mean(axis=1)[:, 0]
    element_part = np.digitize(x, [8.0, 16.0])
    part = partition_from_elements(mesh, element_part)
    counts = shared_counts(mesh, element_part)
    assert counts[0, 2] == 0 and counts[0, 1] > 0 and counts[1, 2] > 0
    pattern = communication_pattern(part)
    expected = tuple(tuple((q, counts[p, q]) for q in range(3) if q != p and counts[p, q] > 0)
                     for p in range(3))
    assert pattern.neighbours == expected
    n0, n1, n2 = part_nodes(mesh, element_part)
    nodes_shared = len((n0 & n1) | (n1 & n2) | (n0 & n2))
    assert pattern.n_interface == nodes_shared
    # the middle part sends two messages and is the slowest
    middle = sum(1e-6 + 24 * counts[1, q] / 1e9 for q in (0, 2))
    assert sync_time(pattern, LINK, "neighbour") == pytest.approx(middle, rel=1e-12)


def test_fit_recovers_latency_and_bandwidth():
    sizes = np.array([8, 1e3, 1e5, 1e6])
    fitted = fit_interconnect(sizes, 2e-6 + sizes / 5e9)
    assert fitted.latency_s == pytest.approx(2e-6, rel=1e-9)
    assert fitted.bandwidth_Bps == pytest.approx(5e9, rel=1e-9)

    rng = np.random.default_rng(0)
    sizes = np.repeat(np.logspace(3, 6, 10), 4)
    noisy = 2e-6 + sizes / 5e9 + rng.normal(0.0, 2e-8, sizes.shape)  # 20 ns noise
    fitted = fit_interconnect(sizes, noisy, name="noisy")
    assert fitted.name == "noisy"
    assert fitted.latency_s == pytest.approx(2e-6, rel=0.05)
    assert fitted.bandwidth_Bps == pytest.approx(5e9, rel=0.01)


def test_fit_refuses_what_it_cannot_resolve():
    with pytest.raises(ProblemError, match="2 distinct"):
        fit_interconnect([100, 100, 100], [1e-6, 1.1e-6, 0.9e-6])
    with pytest.raises(ProblemError, match="too noisy"):  # a negative intercept
        fit_interconnect([1e3, 2e3], [1e-6, 3e-6])
    with pytest.raises(ProblemError, match="too noisy"):  # time falling with size
        fit_interconnect([1e3, 2e3], [3e-6, 1e-6])
    with pytest.raises(ProblemError):
        fit_interconnect([1e3, 2e3], [1e-6])


def test_projection_by_hand():
    pattern = ring_pattern(2, 50)  # S = 1200 bytes
    t_c, t_d = 10e-6, 2e-6
    proj = project(t_c, t_d, pattern, {"test": LINK})
    (row,) = proj.rows
    t_s = 1e-6 + 1.2e-6  # p = 2: one message of S beats two of S/2
    assert row.t_s == pytest.approx(t_s)
    assert row.t_t == pytest.approx(t_c + t_s)
    assert row.t_t_prime == pytest.approx(t_c + t_d)
    assert row.zeta == pytest.approx((t_c + t_s) / (t_c + t_d))
    assert row.break_even_surrogate == pytest.approx(t_s)
    # every preset by default, in order; 10 GbE (15 us, 1.25 GB/s): one message of 1200 B
    proj = project(t_c, t_d, pattern)
    assert [r.interconnect.name for r in proj.rows] == list(INTERCONNECTS)
    ethernet = proj.rows[list(INTERCONNECTS).index("ethernet-10g")]
    assert ethernet.t_s == pytest.approx(15e-6 + 1200 / 1.25e9)
    assert ethernet.zeta == pytest.approx((10e-6 + 15.96e-6) / 12e-6)
    text = proj.table()
    assert "ethernet-10g" in text and "zeta" in text


def test_projection_round_trips_through_json():
    pattern = CommunicationPattern(3, 12, (((1, 10), (2, 5)), ((0, 10),), ((0, 5),)))
    proj = project(5e-6, 1e-6, pattern, algorithm="neighbour")
    data = json.loads(json.dumps(proj.to_dict()))
    assert data == proj.to_dict()
    assert Projection.from_dict(data) == proj


def test_presets_are_documented_and_sane():
    for name in ("shared-memory", "infiniband-hdr", "infiniband-ndr", "nvlink-4", "ethernet-10g",
                 "ethernet-100g"):
        link = INTERCONNECTS[name]
        assert link.name == name and "not measured here" in link.source
        assert 1e-7 < link.latency_s < 1e-4 and 1e9 <= link.bandwidth_Bps <= 1e12
    assert INTERCONNECTS["infiniband-ndr"].bandwidth_Bps == 2 * INTERCONNECTS["infiniband-hdr"].bandwidth_Bps


def test_relative_error():
    assert relative_error(1.1e-6, 1e-6) == pytest.approx(0.1)
    np.testing.assert_allclose(relative_error([1.0, 3.0], [2.0, 2.0]), [-0.5, 0.5])
    with pytest.raises(ProblemError, match="measured"):
        relative_error(1.0, 0.0)


@pytest.mark.parametrize("latency, bandwidth", [(0.0, 1e9), (-1e-6, 1e9), (1e-6, math.inf),
                                                (math.nan, 1e9), (1e-6, "fast")])
def test_bad_interconnects_are_refused(latency, bandwidth):
    with pytest.raises(ConfigError, match="Interconnect"):
        Interconnect("bad", latency, bandwidth)


def test_bad_inputs_are_refused():
    pattern = ring_pattern(2, 50)
    with pytest.raises(ConfigError, match="allreduce-ring"):  # lists the valid names
        sync_time(pattern, LINK, "butterfly")
    with pytest.raises(ConfigError, match="infiniband-hdr"):
        sync_time(pattern, "carrier-pigeon")
    with pytest.raises(ConfigError, match="neighbour"):
        CommunicationPattern(2, 1, (((0, 1),), ((0, 1),)))  # part 0 lists itself
    with pytest.raises(ConfigError, match="one neighbour list per part"):
        CommunicationPattern(3, 1, (((1, 1),), ((0, 1),)))
    with pytest.raises(ProblemError, match="t_compute"):
        project(-1e-6, 1e-6, pattern)
    with pytest.raises(ProblemError, match="t_surrogate"):
        project(1e-6, math.nan, pattern)
    with pytest.raises(ConfigError, match="at least one"):
        project(1e-6, 1e-6, pattern, {})
