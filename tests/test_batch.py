"""`closedloop batch`: one robot calibrated at several dates with a drifting joint offset, on the
serial engine, a local pool and a real Ray cluster (2 CPUs); a bad job isolated; a killed batch
resumed without redoing its finished jobs; drift flagged only when it exceeds its uncertainty."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from closedloop.cli.main import main
from closedloop.errors import InputError
from closedloop.fleet.batch import read_manifest, run_batch
from closedloop.io.logs import JointLog
from closedloop.parallel.executor import get_engine
from closedloop.studies.montecarlo import panda_urdf

NOISE = 1e-4
JOINT = "panda_joint4"
LOOP = "weld:frame=panda_hand,name=fixture"
FIX = ["panda_joint4.x"]  # the length that sets the scale (thesis 3.3), the same on every date


@pytest.fixture(scope="module")
def truth(panda_manifold_weld):
    """A Panda welded to a fixture, 40 configurations spread over the whole self-motion (conftest's, shared
    with the other module of this xdist group)."""
    return panda_manifold_weld


def write_fleet(folder: Path, sc, drifts: list[float], seed: int = 0, broken: bool = False, cv: int = 3) -> Path:
    """One log per date: joint 4's offset has drifted by drifts[i] rad (a reading shifts by -d / scale)."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    k, scale = sc.joints.index(JOINT), sc.truth[f"{JOINT}.scale"]
    jobs = []
    for i, d in enumerate(drifts):
        th = sc.pool.copy()
        th[:, k] -= d / scale
        th += rng.normal(0.0, NOISE, th.shape)
        JointLog(list(sc.joints), th).write_csv(folder / f"arm1-day{i}.csv")
        jobs.append(
            {
                "name": f"arm1-day{i}",
                "robot": "arm1",
                "date": f"2026-03-{i + 1:02d}",
                "log": f"arm1-day{i}.csv",
                "out": f"out/arm1-day{i}",
            }
        )
    if broken:  # a log with a bad value: this job fails, the others do not
        (folder / "broken.csv").write_text(",".join(sc.joints) + "\n" + ",".join(["0.1"] * 6 + ["oops"]) + "\n")
        jobs.insert(
            1, {"name": "arm2-day0", "robot": "arm2", "date": "2026-03-01", "log": "broken.csv", "out": "out/arm2-day0"}
        )
    manifest = folder / "fleet.yaml"
    manifest.write_text(
        yaml.safe_dump(
            {
                "defaults": {"model": panda_urdf(), "loops": [LOOP], "options": {"noise": NOISE, "fix": FIX}, "cv": cv},
                "jobs": jobs,
            }
        )
    )
    return manifest


def params(out: Path) -> dict:
    return json.loads((out / "done.json").read_text())["parameters"]


@pytest.fixture(scope="module")
def cluster():
    import ray  # in the test extra: a real local Ray cluster (imported here, not when a worker collects this file)

    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


@pytest.mark.slow
def test_batch_same_on_every_engine_failure_isolated_drift_flagged(tmp_path, truth, cluster):
    # drift: none, 0.5x and 12x the pair's standard error (~5e-5 rad here)
    drifts = [0.0, 2.5e-5, 6e-4]
    runs = {}
    for engine in ("serial", "local", "ray"):
        man = write_fleet(tmp_path / engine, truth, drifts, broken=True, cv=0)
        with get_engine(engine, jobs=2) as eng:
            runs[engine] = run_batch(read_manifest(man), tmp_path / engine / "summary.csv", eng)
    ref = runs["serial"]
    assert ref.failed == ["arm2-day0"] and len(ref.ran) == 4
    row = {r["name"]: r for r in ref.rows}
    assert row["arm2-day0"]["status"] == "failed" and "oops" in row["arm2-day0"]["error"]
    assert all(row[f"arm1-day{i}"]["status"] == "ok" for i in range(3))
    for engine in ("local", "ray"):
        assert runs[engine].failed == ["arm2-day0"]
        for i in range(3):  # bit-identical calibrations, whichever engine ran them
            assert params(tmp_path / engine / f"out/arm1-day{i}") == params(tmp_path / "serial" / f"out/arm1-day{i}"), (
                engine,
                i,
            )
    # the calibrations see the true drift of the offset, within 4 standard errors of the change (a normal draw
    # exceeds that with probability 6e-5; 3 with 0.27 %)
    p = [params(tmp_path / "serial" / f"out/arm1-day{i}")[f"{JOINT}.offset"] for i in range(3)]
    for i in (1, 2):
        assert abs(p[i][0] - p[0][0] - drifts[i]) < 4 * np.hypot(p[i][1], p[0][1]), (i, p)
    # drift: flagged only for the large change, on that parameter only
    flagged = [(d.after, d.parameter) for d in ref.drift if d.flagged]
    assert flagged == [("arm1-day2", f"{JOINT}.offset")], flagged
    small = next(d for d in ref.drift if d.after == "arm1-day1" and d.parameter == f"{JOINT}.offset")
    assert abs(small.z) < 3 and abs(small.change - 2.5e-5) < 4 * small.se  # not flagged (|z| <= 3), and right
    zs = np.array([d.z for d in ref.drift if not d.flagged])
    assert len(zs) > 20 and 0.5 < zs.std() < 1.5, zs.std()  # the unchanged parameters: z ~ N(0, 1)
    with open(tmp_path / "serial" / "summary.csv") as fh:
        table = list(csv.DictReader(fh))
    assert [r["name"] for r in table] == ["arm1-day0", "arm2-day0", "arm1-day1", "arm1-day2"]
    assert table[3]["drift_flagged"].startswith(f"{JOINT}.offset z=+") and table[2]["drift_flagged"] == ""
    assert float(table[0]["rms_after_mm"]) < 0.1 * float(table[0]["rms_before_mm"])
    assert table[0]["verdict"] == "ok" and table[1]["verdict"] == "n/a"  # the failed job has none
    assert table[0]["top_changes"].startswith(f"{JOINT}.offset=")  # the largest true error (-15 mrad)
    assert (tmp_path / "serial" / "summary.drift.csv").exists()


@pytest.mark.slow
def test_killed_batch_resumes_without_redoing_finished_jobs(tmp_path, truth):
    man = write_fleet(tmp_path, truth, [0.0] * 6, cv=2)
    jobs = read_manifest(man)
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "closedloop.cli.main", "batch", str(man), "--jobs", "2", "--quiet"],
        cwd=tmp_path,
        env=env,
        start_new_session=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    t0 = time.monotonic()
    while sum((j.out / "done.json").exists() for j in jobs) < 2:
        assert proc.poll() is None, proc.stderr.read().decode()
        assert time.monotonic() - t0 < 60, "no job finished within 60 s"
        time.sleep(0.02)
    os.killpg(proc.pid, signal.SIGKILL)  # the CLI and its workers, mid-batch
    proc.wait()
    done = {j.name: (j.out / "done.json").stat().st_mtime_ns for j in jobs if (j.out / "done.json").exists()}
    assert 2 <= len(done) < len(jobs)
    for j in jobs:  # no half job: an output folder exists only whole
        assert not j.out.exists() or {"done.json", "report.json", "calibrated.urdf"} <= {
            p.name for p in j.out.iterdir()
        }
    assert main(["batch", str(man), "--jobs", "2", "--quiet"]) == 0
    for name, mtime in done.items():  # not redone
        assert (tmp_path / "out" / name / "done.json").stat().st_mtime_ns == mtime
    with open(tmp_path / "fleet.summary.csv") as fh:
        table = {r["name"]: r for r in csv.DictReader(fh)}
    assert {n for n, r in table.items() if r["resumed"] == "yes"} == set(done)
    assert all(r["status"] == "ok" for r in table.values()) and len(table) == len(jobs)
    assert all(0 < float(r["cv_test_mm"]) < 1.0 for r in table.values())  # held-out closure at the noise level
    assert not list((tmp_path / "out").glob(".*tmp-*"))  # temporaries of the killed run removed


FIRST_JOB = """
import importlib, json, sys
from closedloop.fleet.batch import read_manifest, run_row
for m in run_row.needs:
    importlib.import_module(m)
before = set(sys.modules)
run_row(read_manifest(sys.argv[1])[0])
print(json.dumps(sorted(m for m in set(sys.modules) - before if m.startswith("closedloop"))))
"""


@pytest.mark.slow
def test_a_worker_s_first_job_imports_only_its_loop_kind(tmp_path, truth):
    """In a fresh process, what a batch job imports as it runs is in `run_row.needs` (imported before its
    clock and time limit start: a worker's first job costs what the others do), all but its loop's kind."""
    man = write_fleet(tmp_path, truth, [0.0], cv=0)
    done = subprocess.run([sys.executable, "-c", FIRST_JOB, str(man)], capture_output=True, text=True, check=True)
    imported = set(json.loads(done.stdout.splitlines()[-1]))
    assert "closedloop.loops.weld" in imported  # (the job ran, and its imports are seen)
    assert imported <= {"closedloop.loops.weld", "closedloop.loops.point"}, sorted(imported)


def test_manifest_csv_and_errors(tmp_path, capsys):
    (tmp_path / "m.csv").write_text(
        "name,robot,date,model,log,loops,noise,identify,out\n"
        f'a,r1,2026-01-02,{panda_urdf()},a.csv,"{LOOP};point:frame=panda_link8,name=tip",1e-4,"placement,offset",o/a\n'
    )
    (job,) = read_manifest(tmp_path / "m.csv")
    assert job.loops == [LOOP, "point:frame=panda_link8,name=tip"] and job.options == {
        "noise": 1e-4,
        "identify": ["placement", "offset"],
    }
    assert job.out == tmp_path / "o" / "a" and job.robot == "r1"
    assert job.cv is None and job.run_options().folds == 5  # as calibrate's --cv: 5, fewer on a shorter log
    (tmp_path / "bad.yaml").write_text("jobs:\n  - {model: m.urdf, out: o}\n")
    with pytest.raises(InputError, match=r"bad.yaml: job 1 .*no 'log'"):
        read_manifest(tmp_path / "bad.yaml")
    (tmp_path / "bad.csv").write_text("model,log,out,colour\nm.urdf,l.csv,o,red\n")
    assert main(["batch", str(tmp_path / "bad.csv")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown key(s) colour" in err[0] and "line 2" in err[0]


def test_a_log_in_degrees_is_refused_as_calibrate_refuses_it(tmp_path, truth, capsys):
    """The job's log read as calibrate reads it (`data.check_angle_units`): refused in one line, not fitted
    for seconds to a `failed` verdict; the other jobs go on."""
    man = write_fleet(tmp_path, truth, [0.0], cv=0)
    JointLog(list(truth.joints), np.degrees(truth.pool)).write_csv(tmp_path / "deg.csv")
    text = yaml.safe_load(man.read_text())
    text["jobs"].append({"name": "deg", "robot": "arm3", "date": "2026-03-01", "log": "deg.csv", "out": "out/deg"})
    man.write_text(yaml.safe_dump(text))
    assert main(["batch", str(man), "--jobs", "1", "--quiet"]) == 1  # a job that could not run
    out, err = capsys.readouterr()
    assert "1 failed" in out and "verdicts: 1 ok" in out
    assert "failed: deg: LogError" in err and "a log in degrees? (give --degrees)" in err


def test_drift_z_and_gauge_check(tmp_path):
    """Results without a gauge record (written by an older closedloop): z = change / sqrt(se1^2 + se2^2),
    |z| > 3 flagged; a pair that estimated other parameters is not compared (no way to put it in one gauge).
    The comparison in one gauge is tested in test_batch_drift.py."""
    from closedloop.fleet.batch import BatchJob, drift

    jobs = [
        BatchJob(f"d{i}", Path("m"), Path("l"), tmp_path / f"d{i}", robot="r", date=f"2026-0{i + 1}-01")
        for i in range(3)
    ]
    ok = {"status": "ok"}
    res = {
        "d0": {
            "row": ok,
            "parameters": {
                "j.x": [1.0, 0.3, "placement"],
                "j.offset": [0.0, 0.1, "offset"],
                "fix.x": [5.0, 0.1, "loop"],
            },
        },
        "d1": {
            "row": ok,
            "parameters": {
                "j.x": [1.4, 0.4, "placement"],
                "j.offset": [0.45, 0.1, "offset"],
                "fix.x": [9.0, 0.1, "loop"],
            },
        },
        "d2": {
            "row": ok,
            "parameters": {
                "j.y": [0.0, 0.1, "placement"],
                "j.offset": [0.35, 0.1, "offset"],
                "fix.x": [9.0, 0.1, "loop"],
            },
        },
    }
    d = drift(list(reversed(jobs)), res)  # ordered by date, not by manifest
    by = {(x.after, x.parameter): x for x in d}
    assert set(by) == {("d1", "j.x"), ("d1", "j.offset"), ("d2", "*")}  # loop parameters left out
    assert by["d1", "j.x"].z == pytest.approx(0.4 / 0.5) and not by["d1", "j.x"].flagged
    assert by["d1", "j.offset"].z == pytest.approx(0.45 / np.sqrt(0.02)) and by["d1", "j.offset"].flagged
    assert "not comparable" in by["d2", "*"].note and "j.x, j.y" in by["d2", "*"].note


def test_an_output_folder_that_is_an_input_is_refused_naming_the_job(tmp_path):
    """The check before the first job finds an output folder that is one of the batch's inputs (a log that
    is a folder, a ROS 2 bag, by inode through a link), looking each input up once."""
    from closedloop.fleet.batch import BatchJob, check_batch_outputs

    for k in range(3):
        (tmp_path / "logs" / f"r{k}").mkdir(parents=True)
    (tmp_path / "link").symlink_to(tmp_path / "logs" / "r1")
    jobs = [
        BatchJob(f"r{k}", Path(panda_urdf()), tmp_path / "logs" / f"r{k}", tmp_path / "out" / f"r{k}") for k in range(3)
    ]
    check_batch_outputs(tmp_path / "m.yaml", jobs, tmp_path / "s.csv")  # distinct folders: accepted
    jobs[2].out = tmp_path / "link"
    with pytest.raises(InputError, match=r"^job r2: out .*link: is an input of the batch \(.*logs/r1\)$"):
        check_batch_outputs(tmp_path / "m.yaml", jobs, tmp_path / "s.csv")


def test_a_manifests_date_written_as_yaml_writes_it_is_read_as_its_text(tmp_path):
    """The fleet guide's manifest writes ``date: 2026-03-02`` unquoted, which YAML reads as a date, not text:
    it is the job's date all the same (it was refused as "not a text value")."""
    man = tmp_path / "fleet.yaml"
    man.write_text(
        "jobs:\n"
        "  - {name: arm1-0302, robot: arm1, date: 2026-03-02, model: m.urdf, log: l.csv, out: o1,"
        " loop: 'weld:frame=panda_hand'}\n"
    )
    (job,) = read_manifest(man)
    assert job.date == "2026-03-02" and job.robot == "arm1"
