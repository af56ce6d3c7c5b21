import pytest

from multicam_ego_motion.coordinator.parallel_time_model import (PAPER_IMPROVEMENT_PCT, predict,
                                                                 sequential_time, table)

EQ = {'acquire': 1.0, 'extract': 4.0, 'track': 3.0, 'pose': 1.5, 'structure': 0.5}   # 10 ms


def equal_rig(n=4):
    return {f'c{i}': [dict(EQ) for _ in range(4)] for i in range(n)}


def test_equal_costs_zero_comm_speedups():
    st = equal_rig()
    assert predict(st, 1).T_par_ms == pytest.approx(160.0)
    assert predict(st, 2).speedup == pytest.approx(2.0)
    assert predict(st, 4).speedup == pytest.approx(4.0)        # M = N: one camera per worker
    assert predict(st, 8).speedup == pytest.approx(8.0)
    assert predict(st, 16).speedup == pytest.approx(16.0)
    # M = 5..7: the floor rule leaves one camera on a single worker -> no gain over M = 4
    assert predict(st, 7).T_par_ms == pytest.approx(40.0)


def test_chunks_follow_equation_2():
    st = equal_rig()
    nf = {c: [200] * 4 for c in st}
    p = predict(st, 64, nf=nf, min_f=50, comm_ms=0.1)        # NP = 4 for every quarter
    assert all(v == 4 for v in p.allocation.chunks.values())
    # eq. (2): 1 + 1.5 + 0.5 + 7 / 4 + comm;  (3): + arbiter (0) + comm;  (4): + comm + GA (0)
    assert p.T_par_ms == pytest.approx(3.0 + 7.0 / 4 + 0.1 + 0.1 + 0.1)


def test_m1_equals_sequential_and_arbiters_are_sequential():
    st = equal_rig()
    arb = {c: 0.5 for c in st}
    p = predict(st, 1, arbiter_ms=arb, general_arbiter_ms=2.0, comm_ms=5.0)
    assert p.T_par_ms == pytest.approx(p.T_seq_ms) and p.T_seq_ms == pytest.approx(160 + 2 + 2)
    assert sequential_time(st, arb, 2.0) == pytest.approx(164.0)
    p4 = predict(st, 4, arbiter_ms=arb, general_arbiter_ms=2.0, comm_ms=0.0)
    assert p4.T_par_ms == pytest.approx(40 + 0.5 + 2.0)      # GA is sequential after all cameras


@pytest.mark.parametrize('comm', [0.0, 0.3])
def test_monotone_non_increasing_in_m(comm):
    st = equal_rig()
    nf = {c: [300, 200, 100, 50] for c in st}
    ts = [predict(st, M, comm_ms=comm, nf=nf, min_f=50, arbiter_ms={c: 0.2 for c in st},
                  general_arbiter_ms=0.5).T_par_ms for M in range(1, 49)]
    assert all(b <= a + 1e-9 for a, b in zip(ts, ts[1:])), ts


def test_communication_costs_only_when_parallel():
    st = equal_rig()
    assert predict(st, 4, comm_ms=1.0).T_par_ms == pytest.approx(predict(st, 4).T_par_ms + 2.0)
    assert predict(st, 1, comm_ms=1.0).T_par_ms == pytest.approx(160.0)


def test_table_rows_carry_paper_figures():
    rows = table(equal_rig(), comm_ms=0.05, nf={f'c{i}': [200] * 4 for i in range(4)}, min_f=50)
    assert [r['M'] for r in rows] == [2, 4, 6, 8, 10, 14, 16, 24, 48]
    assert [r['paper_improvement_pct'] for r in rows] == [48.7, 71.6, 74.8, 80.7, 80.9, 84.86, 85.0, 87.5, 90.5]
    for r in rows:
        assert r['efficiency'] == pytest.approx(r['speedup'] / r['M'])
        assert r['improvement_pct'] == pytest.approx(100 * (1 - 1 / r['speedup']))
    assert PAPER_IMPROVEMENT_PCT[24] == 87.5
    assert table(equal_rig(), [3])[0]['paper_improvement_pct'] is None
