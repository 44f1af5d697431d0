"""Scaling out: the job system on Redis, as on several machines. Two API processes and one worker
process, each with its own state directory, share only a real ``redis-server`` (started here on a
free loopback port) and the NeRF cache directory: a job submitted through one API process is run
by the worker and read back, listed and rendered through the other.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time

import httpx
import pytest
import redis
from job_store_contract import check_store

from model.bundle import export_bundle
from service.jobs.redis_store import RedisJobStore
from service.process import ROOT, ServiceServer, free_port

REDIS_SERVER = shutil.which("redis-server")
pytestmark = pytest.mark.skipif(
    REDIS_SERVER is None,
    reason="redis-server is not installed, so the multi-machine job test cannot run; install it to enable it "
           "(Debian/Ubuntu: `apt-get install -y redis-server`; the test starts its own server on a free loopback port)")


@pytest.fixture(scope="module")
def redis_url(tmp_path_factory):
    port = free_port()
    folder = tmp_path_factory.mktemp("redis")
    process = subprocess.Popen([REDIS_SERVER, "--port", str(port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
                                "--dir", str(folder)], stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
    url = f"redis://127.0.0.1:{port}/0"
    client = redis.Redis.from_url(url)
    deadline = time.monotonic() + 10
    while True:
        try:
            client.ping()
            break
        except redis.ConnectionError:
            if time.monotonic() > deadline or process.poll() is not None:
                process.kill()
                pytest.fail(f"redis-server did not start on port {port}")
            time.sleep(0.05)
    yield url
    process.terminate()
    process.wait(timeout=10)


@pytest.fixture(scope="module")
def machines(trained, chairs, redis_url, tmp_path_factory):
    """API process ``a`` and ``b`` and a worker, sharing Redis and the NeRF cache directory only."""
    run, _ = trained
    root = tmp_path_factory.mktemp("machines")
    bundle = export_bundle(run, root / "bundle", data=chairs)
    shared = {"HYPNERF_BROKER": "redis", "HYPNERF_REDIS_URL": redis_url, "HYPNERF_CACHE_DIR": str(root / "shared-nerfs"),
              "HYPNERF_JOB_LEASE_S": "3", "HYPNERF_TORCH_THREADS": "1"}
    worker_env = {**os.environ, **shared, "OMP_NUM_THREADS": "1", "HYPNERF_WORKERS": "1", "HYPNERF_BUNDLE": str(bundle),
                  "HYPNERF_STATE_DIR": str(root / "worker-state")}
    with open(root / "worker.log", "wb") as log:
        worker = subprocess.Popen([sys.executable, "-m", "service.jobs"], cwd=ROOT, env=worker_env, stdout=log, stderr=subprocess.STDOUT)
    try:
        with ServiceServer(bundle, root / "a-state", env=shared) as a, ServiceServer(bundle, root / "b-state", env=shared) as b:
            yield {"a": a, "b": b, "worker_log": root / "worker.log"}
    finally:
        worker.terminate()
        worker.wait(timeout=20)


def test_the_redis_store_keeps_the_lifecycle_promises(redis_url):
    check_store(RedisJobStore(redis_url, prefix="contract"))


def test_a_job_submitted_to_one_replica_is_run_by_a_worker_and_read_from_another(machines, chairs):
    folder = min(p for p in chairs.iterdir() if p.is_dir())
    frame = json.loads((folder / "transforms.json").read_text())["frames"][0]
    files = [("images", ("view.png", (folder / frame["file_path"]).read_bytes(), "image/png"))]
    data = {"poses": json.dumps([frame["transform_matrix"]]), "options": json.dumps({"steps": 10, "rays_per_step": 128, "init": "mean"})}
    with httpx.Client(base_url=machines["a"].url, timeout=60) as a, httpx.Client(base_url=machines["b"].url, timeout=60) as b:
        submitted = a.post("/v1/jobs/inversions", files=files, data=data, headers={"Idempotency-Key": "scale-out"})
        assert submitted.status_code == 202, submitted.text
        job_id = submitted.json()["id"]
        # the idempotency key holds across replicas
        assert b.post("/v1/jobs/inversions", files=files, data=data, headers={"Idempotency-Key": "scale-out"}).json()["id"] == job_id
        deadline = time.monotonic() + 90
        while (job := b.get(f"/v1/jobs/{job_id}").json())["status"] not in ("succeeded", "failed", "canceled"):
            assert time.monotonic() < deadline, f"job not finished: {job}\n{machines['worker_log'].read_text()[-3000:]}"
            time.sleep(0.2)
        assert job["status"] == "succeeded", job
        assert job["worker"] is None and job["attempts"] == 1
        assert job_id in [j["id"] for j in b.get("/v1/jobs", params={"status": "succeeded"}).json()["items"]]
        render = b.get(f"/v1/nerfs/{job['result']['nerf_id']}/render", params={"width": 24, "height": 24})
        assert render.status_code == 200 and render.headers["content-type"] == "image/png"
        metrics = a.get("/metrics").text
        assert 'hypnerf_jobs_finished_total{status="succeeded"} 1.0' in metrics
        denoise = a.post("/v1/jobs/inversions", files=files, data={**data, "options": json.dumps({"steps": 10, "denoise": True})})
        assert denoise.status_code == 422 and "no denoiser" in denoise.json()["detail"]
