"""Inversion jobs against the real thing: ``hypnerf serve`` in a subprocess with a tiny bundle from
the real exporter, the SQLite jobs table, huey's consumer with worker processes, a loopback webhook
receiver. Covers the lifecycle to a rendered result, progress over server-sent events, idempotency,
listing, cancel (queued and running), the queue's 429, signed webhooks (retried, refused targets),
bad inputs answered 4xx problem+json, and a worker or the whole server killed with SIGKILL while a
job runs: the job is re-queued and succeeds exactly once.
"""

from __future__ import annotations

import hashlib
import hmac
import io
import json
import math
import os
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import httpx
import numpy as np
import pytest
from job_store_contract import check_store
from PIL import Image

from model.bundle import export_bundle
from model.denoise.io import save_denoiser
from model.denoise.vqvae import VQVAE2Denoiser, tiny_config
from service.jobs.store import SqliteJobStore
from service.problems import PROBLEM_JSON
from service.process import ServiceServer, free_port

SECRET = "webhook-secret-for-tests"
LEASE_S = 3.0
QUICK = {"steps": 12, "rays_per_step": 128, "init": "mean"}  # seconds of work on two loaded cores
# seconds of work even on an idle machine: long enough to be seen running (progress is stored every
# 0.5 s) and to be killed mid-job
STEADY = {"steps": 300, "rays_per_step": 1024, "init": "mean"}
LONG = {"steps": 400, "rays_per_step": 64, "init": "mean"}  # runs until canceled or killed
ENV = {
    "HYPNERF_WORKERS": "1", "HYPNERF_TORCH_THREADS": "1", "HYPNERF_JOB_LEASE_S": str(LEASE_S),
    "HYPNERF_WEBHOOK_ALLOW": "127.0.0.1", "HYPNERF_WEBHOOK_SECRET": SECRET,
    "HYPNERF_LIMITS__MAX_QUEUED_JOBS": "3", "HYPNERF_LIMITS__MAX_TTO_STEPS": "400",
    "HYPNERF_LIMITS__MAX_IMAGE_PIXELS": "5000", "HYPNERF_LIMITS__MAX_BODY_BYTES": "300000",
}


# -- fixtures: bundle, views, server, webhook receiver ----------------------------------------------


@pytest.fixture(scope="module")
def jobs_bundle(trained, chairs, tmp_path_factory) -> Path:
    """The tiny prior with an untrained tiny denoiser: it exercises the denoise-and-finetune path."""
    run, _ = trained
    root = tmp_path_factory.mktemp("jobs")
    denoiser = save_denoiser(root / "denoiser", VQVAE2Denoiser(tiny_config()))
    return export_bundle(run, root / "bundle", data=chairs, denoiser=denoiser)


@pytest.fixture(scope="module")
def views(chairs) -> list[tuple[bytes, list]]:
    """Two (PNG bytes, 4x4 pose) views of one training chair."""
    folder = min(p for p in chairs.iterdir() if p.is_dir())
    frames = json.loads((folder / "transforms.json").read_text())["frames"]
    return [((folder / frames[i]["file_path"]).read_bytes(), frames[i]["transform_matrix"]) for i in (0, 7)]


class Receiver:
    """A loopback webhook receiver recording every POST; answers 500 to the first ``fail_first``
    requests of a path, then 200."""

    def __init__(self):
        self.calls: list[dict] = []
        self.fail_first: dict[str, int] = {}
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self):
                body = self.rfile.read(int(self.headers["Content-Length"]))
                receiver.calls.append({"path": self.path, "headers": dict(self.headers), "body": body})
                failing = receiver.fail_first.get(self.path, 0)
                receiver.fail_first[self.path] = max(0, failing - 1)
                self.send_response(500 if failing else 200)
                self.end_headers()

            def log_message(self, *args):
                pass

        self.port = free_port()
        self.http = ThreadingHTTPServer(("127.0.0.1", self.port), Handler)
        threading.Thread(target=self.http.serve_forever, daemon=True).start()

    def url(self, path: str) -> str:
        return f"http://127.0.0.1:{self.port}{path}"

    def to(self, path: str) -> list[dict]:
        return [call for call in self.calls if call["path"] == path]


@pytest.fixture(scope="module")
def receiver():
    running = Receiver()
    yield running
    running.http.shutdown()


@pytest.fixture(scope="module")
def server(jobs_bundle, tmp_path_factory):
    with ServiceServer(jobs_bundle, tmp_path_factory.mktemp("jobs-state"), env=ENV) as running:
        yield running


@pytest.fixture(scope="module")
def client(server):
    with httpx.Client(base_url=server.url, timeout=60.0) as http:
        yield http


# -- helpers ----------------------------------------------------------------------------------------


def submit(client, views, options=None, *, poses=None, images=None, masks=None, key=None) -> httpx.Response:
    files = [("images", (f"view{i}.png", data, "image/png")) for i, data in enumerate(images or [v[0] for v in views])]
    files += [("masks", (f"mask{i}.png", data, "image/png")) for i, data in enumerate(masks or [])]
    data = {"options": json.dumps(options if options is not None else QUICK)}
    if poses is not False:
        data["poses"] = json.dumps(poses if poses is not None else [v[1] for v in views])
    return client.post("/v1/jobs/inversions", files=files, data=data, headers={"Idempotency-Key": key} if key else {})


def wait_for(client, job_id: str, condition, timeout: float = 90.0) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        job = client.get(f"/v1/jobs/{job_id}").json()
        if condition(job):
            return job
        time.sleep(0.1)
    raise AssertionError(f"job {job_id} did not get there in {timeout:.0f} s; last seen: {job}")


def finished(job: dict) -> bool:
    return job["status"] in ("succeeded", "failed", "canceled")


def running_with_progress(job: dict) -> bool:
    return job["status"] == "running" and job["progress"] is not None


def assert_problem(response: httpx.Response, status: int) -> dict:
    assert response.status_code == status, response.text
    assert response.headers["content-type"] == PROBLEM_JSON
    body = response.json()
    assert body["status"] == status and body["title"] and body.get("detail") and "Traceback" not in response.text
    return body


def png(width: int, height: int, rgba=(200, 30, 30, 255)) -> bytes:
    out = io.BytesIO()
    Image.new("RGBA", (width, height), rgba).save(out, format="PNG")
    return out.getvalue()


def alive(pid: int) -> bool:
    """Whether ``pid`` is a live process (a zombie waiting to be reaped counts as gone)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return False
    return state != "Z"


def wait_gone(pid: int, timeout: float = 15.0) -> None:
    deadline = time.monotonic() + timeout
    while alive(pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not alive(pid), f"process {pid} outlived its server"


def worker_pid(job: dict) -> int:
    return int(job["worker"].split(":")[1])


def signed(call: dict) -> dict:
    expected = "sha256=" + hmac.new(SECRET.encode(), call["body"], hashlib.sha256).hexdigest()
    assert hmac.compare_digest(call["headers"]["X-Hypnerf-Signature"], expected)
    return json.loads(call["body"])


# -- the store ----------------------------------------------------------------------------------------


def test_the_sqlite_store_keeps_the_lifecycle_promises(tmp_path):
    check_store(SqliteJobStore(tmp_path / "jobs.db"))


# -- bad input ----------------------------------------------------------------------------------------


def _rotated(pose: list, scale: float) -> list:
    bad = np.array(pose, dtype=float)
    bad[:3, :3] *= scale
    return bad.tolist()


def _inside(pose: list) -> list:
    bad = np.array(pose, dtype=float)
    bad[:3, 3] = 0.0
    return bad.tolist()


def _nan(pose: list) -> list:
    bad = np.array(pose, dtype=float)
    bad[0, 3] = math.nan
    return bad.tolist()


BAD = {
    "no image": (422, lambda v: {"images": []}),
    "not an image": (415, lambda v: {"images": [b"this is text, not a picture", v[1][0]]}),
    "too many pixels": (413, lambda v: {"images": [png(100, 100), png(100, 100)]}),
    "body too large": (413, lambda v: {"images": [os.urandom(320_000), v[1][0]]}),
    "sizes differ": (422, lambda v: {"images": [v[0][0], png(16, 16)]}),
    "scaled rotation": (422, lambda v: {"poses": [_rotated(v[0][1], 1.5), v[1][1]]}),
    "mirrored rotation": (422, lambda v: {"poses": [_rotated(v[0][1], -1.0), v[1][1]]}),
    "non-finite pose": (422, lambda v: {"poses": [_nan(v[0][1]), v[1][1]]}),
    "camera inside the box": (422, lambda v: {"poses": [_inside(v[0][1]), v[1][1]]}),
    "pose not 4x4": (422, lambda v: {"poses": [[[1, 0, 0], [0, 1, 0], [0, 0, 1]], v[1][1]]}),
    "wrong number of poses": (422, lambda v: {"poses": [v[0][1]]}),
    "poses not JSON": (422, lambda v: {"poses_text": "[[1, 2"}),
    "orbit elevation out of range": (422, lambda v: {"poses": [{"azimuth": 0, "elevation": 95}, v[1][1]]}),
    "two images without poses": (422, lambda v: {"poses": False}),
    "steps over the cap": (422, lambda v: {"options": {"steps": 401}}),
    "steps and finetune over the cap": (422, lambda v: {"options": {"steps": 300, "finetune_steps": 200}}),
    "unknown option": (422, lambda v: {"options": {"stpes": 10}}),
    "denoise steps over the cap": (422, lambda v: {"options": {"steps": 200, "denoise": True}}),
    # 100 + 160 would fit; every round's steps count
    "denoise rounds over the cap": (422, lambda v: {"options": {"steps": 100, "denoise": True, "denoise_steps": 160, "denoise_rounds": 2}}),
    "no denoise round": (422, lambda v: {"options": {"steps": 10, "denoise": True, "denoise_rounds": 0}}),
    "denoise settings without denoise": (422, lambda v: {"options": {"steps": 10, "denoise_mirror": False}}),
    "denoise mirror not a boolean": (422, lambda v: {"options": {"steps": 10, "denoise": True, "denoise_mirror": "sideways"}}),
    "webhook host not allowed": (422, lambda v: {"options": {"steps": 10, "webhook_url": "http://example.com/hook"}}),
    "webhook not http": (422, lambda v: {"options": {"steps": 10, "webhook_url": "file:///etc/passwd"}}),
    "one mask for two images": (422, lambda v: {"masks": [png(32, 32, (255, 255, 255, 255))]}),
    "empty masks": (422, lambda v: {"masks": [png(32, 32, (0, 0, 0, 255))] * 2}),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_submissions_are_4xx_problems(client, views, case):
    status, change = BAD[case]
    spec = change(views)
    if "poses_text" in spec:
        files = [("images", (f"v{i}.png", v[0], "image/png")) for i, v in enumerate(views)]
        response = client.post("/v1/jobs/inversions", files=files, data={"poses": spec["poses_text"]})
    elif spec.get("images") == []:
        response = client.post("/v1/jobs/inversions", data={"poses": json.dumps([v[1] for v in views])})
    else:
        response = submit(client, views, spec.get("options"), poses=spec.get("poses"), images=spec.get("images"), masks=spec.get("masks"))
    assert_problem(response, status)


def test_unknown_jobs_and_cursors_are_problems(client):
    assert_problem(client.get("/v1/jobs/" + "0" * 32), 404)
    assert_problem(client.post("/v1/jobs/nope/cancel"), 404)
    assert_problem(client.get("/v1/jobs/nope/events"), 404)
    assert_problem(client.get("/v1/jobs", params={"cursor": "not-a-cursor"}), 422)
    assert_problem(client.get("/v1/jobs", params={"status": "sleeping"}), 422)


# -- the lifecycle ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def done(client, views, receiver) -> dict:
    """A job followed over server-sent events to the end: (the job, its events)."""
    options = {**STEADY, "steps": 150, "webhook_url": receiver.url("/done")}
    receiver.fail_first["/done"] = 1  # the first delivery fails: it is retried
    response = submit(client, views, options, key="lifecycle-1")
    assert response.status_code == 202, response.text
    job = response.json()
    assert response.headers["location"] == f"/v1/jobs/{job['id']}" and job["status"] == "queued"
    events = []
    with client.stream("GET", f"/v1/jobs/{job['id']}/events", timeout=120.0) as stream:
        assert stream.headers["content-type"].startswith("text/event-stream")
        for line in stream.iter_lines():
            if line.startswith("data: "):
                events.append(json.loads(line[len("data: "):]))
    return {"options": options, "submitted": job, "events": events, "job": client.get(f"/v1/jobs/{job['id']}").json()}


def test_a_job_runs_to_a_nerf_that_renders(client, done):
    job = done["job"]
    assert job["status"] == "succeeded" and job["attempts"] == 1 and job["error"] is None, job
    result = job["result"]
    assert result["steps"] <= done["options"]["steps"] and np.isfinite(result["psnr"]) and not result["finetuned"]
    assert len(result["codes"]["shape"]) > 0 and all(np.isfinite(result["codes"]["color"]))
    nerf = client.get(f"/v1/nerfs/{result['nerf_id']}")
    assert nerf.status_code == 200 and nerf.json()["source"]["inversion"] == job["id"]
    render = client.get(f"/v1/nerfs/{result['nerf_id']}/render", params={"width": 32, "height": 32})
    assert render.status_code == 200 and render.headers["content-type"] == "image/png"
    pixels = np.asarray(Image.open(io.BytesIO(render.content)))
    assert pixels.shape[:2] == (32, 32) and pixels.std() > 0  # something was rendered, not a blank image


def test_progress_streams_until_the_end(done):
    events = done["events"]
    assert events[-1]["status"] == "succeeded"
    steps = [e["progress"]["step"] for e in events if e["progress"]]
    assert len(steps) >= 2 and steps == sorted(steps) and steps[0] < steps[-1], steps
    running = [e for e in events if e["status"] == "running" and e["progress"]]
    assert all(e["progress"]["steps"] == done["options"]["steps"] and e["progress"]["eta_s"] >= 0 for e in running)


def test_the_webhook_is_signed_retried_and_recorded(client, done, receiver):
    job_id = done["job"]["id"]
    job = wait_for(client, job_id, lambda j: (j["webhook"] or {}).get("delivered") is not None, timeout=30)
    calls = receiver.to("/done")
    assert len(calls) == 2  # one 500, then accepted
    bodies = [signed(call) for call in calls]
    assert all(body["id"] == job_id and body["status"] == "succeeded" for body in bodies)
    assert calls[1]["headers"]["X-Hypnerf-Event"] == "job.succeeded"
    assert job["webhook"]["delivered"] is True and job["webhook"]["attempts"] == 2 and job["webhook"]["status_code"] == 200


def test_idempotency_key_returns_the_same_job_or_409(client, views, done):
    again = submit(client, views, done["options"], key="lifecycle-1")
    assert again.status_code == 202 and again.json()["id"] == done["job"]["id"]
    assert again.headers["idempotent-replayed"] == "true"
    assert_problem(submit(client, views, {**done["options"], "seed": 1}, key="lifecycle-1"), 409)


def test_jobs_are_listed_newest_first_with_a_status_filter(client, done):
    job_id = done["job"]["id"]
    succeeded = client.get("/v1/jobs", params={"status": "succeeded"}).json()["items"]
    assert job_id in [j["id"] for j in succeeded] and all(j["status"] == "succeeded" for j in succeeded)
    assert job_id not in [j["id"] for j in client.get("/v1/jobs", params={"status": "queued"}).json()["items"]]
    first = client.get("/v1/jobs", params={"limit": 1}).json()
    if first["next"] is not None:
        second = client.get("/v1/jobs", params={"limit": 1, "cursor": first["next"]}).json()
        assert second["items"][0]["created_at"] <= first["items"][0]["created_at"]
        assert second["items"][0]["id"] != first["items"][0]["id"]
    assert_problem(client.post(f"/v1/jobs/{job_id}/cancel"), 409)  # finished: nothing to cancel


def test_finetune_and_denoise_make_a_finetuned_nerf(client, views):
    options = {**QUICK, "steps": 6, "finetune_steps": 3, "denoise": True, "denoise_steps": 4, "denoise_rounds": 2,
               "denoise_mirror": True}
    job = wait_for(client, submit(client, views, options).json()["id"], finished)
    assert job["status"] == "succeeded", job
    assert job["result"]["finetuned"] and job["result"]["steps"] <= 6 + 3 + 2 * 4 and job["progress"]["steps"] == 6 + 3 + 2 * 4
    nerf = client.get(f"/v1/nerfs/{job['result']['nerf_id']}").json()
    assert nerf["codes"] is None and nerf["source"] == {"inversion": job["id"], "finetuned": True}


def test_a_photo_of_another_size_is_denoised_and_finetuned(client, views):
    from PIL import Image

    original = Image.open(io.BytesIO(views[0][0]))
    photo = io.BytesIO()
    original.resize((original.width + 8, original.height - 6)).save(photo, format="PNG")  # non-square, not the bundle camera's size
    options = {**QUICK, "steps": 4, "denoise": True, "denoise_steps": 3, "denoise_rounds": 1}
    job = wait_for(client, submit(client, views, options, images=[photo.getvalue()], poses=[views[0][1]]).json()["id"], finished)
    assert job["status"] == "succeeded", job
    assert job["result"]["finetuned"] and client.get(f"/v1/nerfs/{job['result']['nerf_id']}/render", params={"width": 16, "height": 16}).status_code == 200


def test_one_image_without_a_pose_is_inverted_with_a_pose_search(client, views):
    job = wait_for(client, submit(client, views, {**QUICK, "steps": 4}, poses=False, images=[views[0][0]]).json()["id"], finished)
    assert job["status"] == "succeeded", job
    assert client.get(f"/v1/nerfs/{job['result']['nerf_id']}/render", params={"width": 16, "height": 16}).status_code == 200


def test_events_of_a_finished_job_end_at_once(client, done):
    response = client.get(f"/v1/jobs/{done['job']['id']}/events")
    events = [json.loads(line[6:]) for line in response.text.splitlines() if line.startswith("data: ")]
    assert len(events) == 1 and events[0]["status"] == "succeeded"


# -- cancel and back-pressure -------------------------------------------------------------------------


def test_cancel_queued_and_running_jobs_and_a_full_queue_answers_429(client, views, receiver):
    running = submit(client, views, {**LONG, "webhook_url": receiver.url("/canceled")}).json()
    wait_for(client, running["id"], running_with_progress)
    queued = [submit(client, views, {**LONG, "seed": seed}).json() for seed in (1, 2)]
    refused = submit(client, views, {**LONG, "seed": 3})
    assert_problem(refused, 429)
    assert int(refused.headers["retry-after"]) >= 1

    canceled = client.post(f"/v1/jobs/{queued[1]['id']}/cancel")
    assert canceled.status_code == 200 and canceled.json()["status"] == "canceled"  # queued: at once
    assert client.post(f"/v1/jobs/{queued[0]['id']}/cancel").json()["status"] == "canceled"
    asked = client.post(f"/v1/jobs/{running['id']}/cancel").json()
    assert asked["cancel_requested"] and asked["status"] in ("running", "canceled")
    stopped = wait_for(client, running["id"], finished, timeout=30)
    assert stopped["status"] == "canceled" and stopped["result"] is None
    assert stopped["progress"]["step"] < LONG["steps"]
    assert client.post(f"/v1/jobs/{running['id']}/cancel").status_code == 200  # canceling again is a no-op
    wait_for(client, running["id"], lambda j: (j["webhook"] or {}).get("delivered"), timeout=30)
    assert [signed(call)["status"] for call in receiver.to("/canceled")] == ["canceled"]
    listed = client.get("/v1/jobs", params={"status": "canceled"}).json()["items"]
    assert {running["id"], *(j["id"] for j in queued)} <= {j["id"] for j in listed}


def test_metrics_count_jobs_by_status_and_duration(client, done):
    text = client.get("/metrics").text
    assert "hypnerf_jobs_queue_depth 0.0" in text
    assert 'hypnerf_jobs_finished_total{status="succeeded"}' in text
    succeeded = float(text.split('hypnerf_jobs_finished_total{status="succeeded"} ')[1].split()[0])
    durations = float(text.split("hypnerf_job_duration_seconds_count ")[1].split()[0])
    assert succeeded >= 1 and durations >= succeeded


# -- workers and servers killed mid-job -----------------------------------------------------------------


def test_a_killed_worker_s_job_is_requeued_and_succeeds_once(client, views, receiver):
    options = {**STEADY, "webhook_url": receiver.url("/worker-killed")}
    job = submit(client, views, options).json()
    first = wait_for(client, job["id"], running_with_progress)
    os.kill(worker_pid(first), 9)
    done = wait_for(client, job["id"], finished)
    assert done["status"] == "succeeded" and done["attempts"] >= 2, done
    assert not alive(worker_pid(first))
    wait_for(client, job["id"], lambda j: (j["webhook"] or {}).get("delivered"), timeout=30)
    time.sleep(1.0)
    assert [signed(call)["status"] for call in receiver.to("/worker-killed")] == ["succeeded"]


def test_a_server_killed_mid_job_restarts_and_the_job_succeeds_once(server, views, receiver):
    with httpx.Client(base_url=server.url, timeout=60.0) as http:
        job = submit(http, views, {**STEADY, "webhook_url": receiver.url("/server-killed")}).json()
        first = wait_for(http, job["id"], running_with_progress)
    server.kill()
    wait_gone(worker_pid(first))  # the workers follow their server out
    server.start()
    with httpx.Client(base_url=server.url, timeout=60.0) as http:
        done = wait_for(http, job["id"], finished)
        assert done["status"] == "succeeded" and done["attempts"] == 2, done
        wait_for(http, job["id"], lambda j: (j["webhook"] or {}).get("delivered"), timeout=30)
        assert http.get(f"/v1/nerfs/{done['result']['nerf_id']}/render", params={"width": 16, "height": 16}).status_code == 200
        earlier = http.get("/v1/jobs", params={"status": "succeeded"}).json()["items"]
        assert len(earlier) >= 3  # finished jobs survive the restart
    time.sleep(1.0)
    assert [signed(call)["status"] for call in receiver.to("/server-killed")] == ["succeeded"]
