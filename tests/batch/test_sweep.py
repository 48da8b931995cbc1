"""The plant-wide sweep on a Dask distributed cluster (a LocalCluster in this process) gives the rows the
sequential sweep gives."""

from __future__ import annotations

import distributed  # the optional extra valve_emulator[cluster]: CI installs it
import pytest
from historian import STEPS_300, simulate

from valve_emulator.batch.sweep import recordings_in, sweep
from valve_emulator.recordings.recording import write_csv


def _folder(tmp_path):
    write_csv(simulate([3.0], [10.0, 1.0], 10.0, 0.2, 10.0, S=5.0, J=2.0, duration=700.0), tmp_path / "a.csv")
    write_csv(simulate([2.0], [12.0, 1.0], 4.0, 0.5, 12.0, duration=900.0, sp_steps=STEPS_300), tmp_path / "b.csv")
    return tmp_path


@pytest.mark.slow
def test_the_sweep_on_a_local_dask_cluster_matches_the_sequential_sweep(tmp_path):
    folder = _folder(tmp_path)
    seen = []
    with distributed.LocalCluster(processes=False, n_workers=1, threads_per_worker=1,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        rows = sweep([folder], scheduler=client, progress=lambda done, total, row: seen.append((done, total)))
    local = sweep([folder])
    assert sorted(seen) == [(1, 2), (2, 2)]
    assert [r["answer"] for r in rows] == [r["answer"] for r in local] == ["stiction", "no_stiction"]
    assert rows[0]["S"] == pytest.approx(local[0]["S"], rel=1e-9)


def test_a_missing_path_and_an_empty_folder_are_refused_by_name(tmp_path):
    with pytest.raises(ValueError, match="nope: no such file or folder"):
        recordings_in([tmp_path / "nope"])
    with pytest.raises(ValueError, match="no recording files"):
        recordings_in([tmp_path])
