"""warpfem.tradeoff on a Dask cluster: an embedded local cluster of 2 worker processes (127.0.0.1
only) gives the same study as the serial run apart from timings; a worker that dies is retried
and reported, and a job that keeps failing comes back as a failed row."""

import os

import pytest

distributed = pytest.importorskip("distributed", reason="needs the dask extra: pip install 'warpfem[dask]'")

from warpfem.tradeoff import TradeoffConfig, TradeoffGrid, TruthSpec, run_study  # noqa: E402
from warpfem.tradeoff.cluster import DaskExecutor, JobFailed, _die_once  # noqa: E402
from warpfem.tradeoff.study import without_timings  # noqa: E402

from tiny_scenes import tiny_beam_toml  # noqa: E402

BEAM = tiny_beam_toml("tiny_beam", cells=4, frames=2)


@pytest.fixture(scope="module")
def cluster():
    with DaskExecutor(workers=2, retries=1) as ex:
        yield ex


def test_cluster_binds_to_localhost_only(cluster):
    addrs = cluster.worker_addresses() + [cluster.client.scheduler_info()["address"]]
    assert len(cluster.worker_addresses()) == 2
    assert all(a.startswith("tcp://127.0.0.1:") for a in addrs), addrs


def test_study_on_the_cluster_equals_the_serial_study(cluster, tmp_path):
    p = tmp_path / "beam.toml"
    p.write_text(BEAM)
    ref = TradeoffConfig(name="reference", tol=1e-9, cg_tol=1e-9, max_iters=100, max_cg_iters=20000, substeps=2)
    grid = TradeoffGrid(configs=[TradeoffConfig(name="scene"), TradeoffConfig(name="f32 loose", precision="float32", tol=1e-3,
                                                                            cg_tol=1e-2),
                                 TradeoffConfig(name="hex8", element="hex8")],
                        reference=ref, frames=2, truth=TruthSpec(refine=2, substeps=2))
    serial = run_study(str(p), grid)
    dask = run_study(str(p), grid, executor=cluster)
    a, b = without_timings(serial), without_timings(dask)
    assert a == b  # bit-identical trajectories and errors, same rows in the same order
    assert dask.executor.startswith("dask") and serial.executor.startswith("serial")
    workers = {r.ran_on.split("dask worker ")[-1] for r in dask.results}
    assert all("dask worker tcp://127.0.0.1:" in r.ran_on for r in dask.results)
    assert workers <= set(cluster.worker_addresses()) | workers  # timed where they ran
    by = {r.name: r for r in dask.results}
    assert all(r.status == "ok" for r in dask.results)
    assert by["hex8"].discretisation_tip_error > 0 and by["scene"].solver_tip_error > 0
    assert all(r.seconds_per_sim_second > 0 for r in dask.results)


def test_a_dead_worker_is_retried_and_reported(cluster, tmp_path):
    jobs = [{"marker": str(tmp_path / "m0"), "value": 21}]
    out = cluster.map(_die_once, jobs)
    assert out == [42] and os.path.exists(tmp_path / "m0")
    assert len(cluster.retried[0]) == 1 and "worker died" in cluster.retried[0][0]


def test_a_job_that_keeps_killing_its_worker_is_reported_failed(cluster, tmp_path):
    out = cluster.map(_die_once, [{"marker": str(tmp_path / "m1"), "value": 1, "always": True}])
    assert isinstance(out[0], JobFailed) and out[0].attempts == 2  # retries=1
    assert "worker died" in out[0].message


def test_missing_distributed_names_the_extra(monkeypatch):
    import sys

    from warpfem.tradeoff.cluster import require_distributed

    monkeypatch.setitem(sys.modules, "distributed", None)
    with pytest.raises(ImportError, match=r"warpfem\[dask\]"):
        require_distributed()


def test_tune_on_the_cluster_picks_what_the_serial_search_picks(cluster, tmp_path):
    from warpfem.tradeoff.tune import tune

    p = tmp_path / "beam.toml"
    p.write_text(BEAM)
    axes = {"element": ["tet4"], "substeps": [1, 2, 4], "tol": [1e-3], "cg_tol": [1e-2], "precision": ["float64"]}
    kw = dict(frames=2, axes=axes, truth=None, cost="work")  # the tight run on the scene mesh: a short test
    serial = tune(str(p), 0.3, **kw)
    dask = tune(str(p), 0.3, executor=cluster, **kw)
    assert serial.winner is not None and dask.winner is not None
    assert dask.winner["config"] == serial.winner["config"]
    assert dask.winner["error"] == serial.winner["error"] and dask.winner["work"] == serial.winner["work"]
    assert "dask worker tcp://127.0.0.1:" in dask.winner["ran_on"]
