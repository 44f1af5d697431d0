"""The Python SDK (``clients/python``, package ``hypnerf_client``) against the real thing:
``hypnerf serve`` (uvicorn) in a subprocess with a tiny bundle from the real exporter, API keys
on, one inversion worker process. Every SDK method; the error hierarchy mapped from the server's
problem+json (401, 404, 409, 413, 415, 422, 429 with ``Retry-After`` honoured by retries, 501);
refused connections retried until the server's port opens; ``AsyncClient`` parity; an
inversion job followed by ``jobs.wait`` and by server-sent events; and the README's examples,
run as written. The retry policy and the event-stream decoder are also checked on their own.

``make install`` installs the SDK into the venv; before that has run, the SDK is imported from
``clients/python`` (and the installation test says so by skipping).
"""

from __future__ import annotations

import asyncio
import email.utils
import io
import itertools
import json
import os
import re
import socket
import socketserver
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from PIL import Image

from model.bundle import export_bundle
from model.data.cameras import look_at, spherical_direction
from service.process import ServiceServer, free_port

ROOT = Path(__file__).resolve().parents[1]
SDK = ROOT / "clients" / "python"
try:
    import hypnerf_client
    INSTALLED = True
except ImportError:  # `make install` has not run since the SDK was added: use the source tree
    sys.path.insert(0, str(SDK))
    import hypnerf_client
    INSTALLED = False

from hypnerf_client import (
    APIError,
    AsyncClient,
    AuthenticationError,
    Client,
    ConflictError,
    HypnerfError,
    InversionOptions,
    JobCanceledError,
    JobFailedError,
    JobTimeoutError,
    NotFoundError,
    NotImplementedByServerError,
    PayloadTooLargeError,
    RateLimitError,
    UnsupportedMediaError,
    ValidationError,
)
from hypnerf_client._calls import JobWatch
from hypnerf_client._retry import RetryPolicy, retry_after_seconds
from hypnerf_client._sse import SSEDecoder
from hypnerf_client.types import Job

KEY = "sdk-test-key-0123456789"
QUICK = InversionOptions(steps=12, rays_per_step=128, init="mean")  # seconds of work on two loaded cores
LONG = {"steps": 400, "rays_per_step": 64, "init": "mean"}  # runs until canceled
ENV = {
    "HYPNERF_API_KEYS": KEY, "HYPNERF_WORKERS": "1", "HYPNERF_TORCH_THREADS": "1", "HYPNERF_JOB_LEASE_S": "3",
    "HYPNERF_LIMITS__MAX_BODY_BYTES": "300000", "HYPNERF_LIMITS__MAX_QUEUED_JOBS": "1", "HYPNERF_LIMITS__MAX_TTO_STEPS": "400",
    "HYPNERF_LIMITS__MAX_RENDER_SIDE": "256",
}


@pytest.fixture(scope="module")
def server(trained, chairs, tmp_path_factory):
    run, _ = trained
    bundle = export_bundle(run, tmp_path_factory.mktemp("sdk") / "bundle", data=chairs)
    with ServiceServer(bundle, tmp_path_factory.mktemp("sdk-state"), env=ENV) as running:
        yield running


@pytest.fixture(scope="module")
def client(server):
    with Client(server.url, api_key=KEY) as sdk:
        yield sdk


@pytest.fixture(scope="module")
def views(chairs) -> tuple[list[Path], list[np.ndarray]]:
    """Two views of one training chair: image paths and 4x4 camera-to-world poses."""
    folder = min(p for p in chairs.iterdir() if p.is_dir())
    frames = json.loads((folder / "transforms.json").read_text())["frames"]
    chosen = [frames[0], frames[7]]
    return [folder / f["file_path"] for f in chosen], [np.array(f["transform_matrix"]) for f in chosen]


def _pixels(png: bytes) -> np.ndarray:
    image = Image.open(io.BytesIO(png))
    assert image.format == "PNG"
    return np.asarray(image)


def _until(predicate, timeout: float = 60.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"not reached in {timeout:.0f} s")


def _sdk_env(url: str) -> dict[str, str]:
    env = {**os.environ, "HYPNERF_URL": url, "HYPNERF_API_KEY": KEY}
    if not INSTALLED:
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(SDK), env.get("PYTHONPATH")]))
    return env


# -- the package --------------------------------------------------------------------------------------


def test_the_venv_has_the_sdk_installed(tmp_path):
    if not INSTALLED:
        pytest.skip("hypnerf_client is not installed in this venv yet (`make install` installs it); imported from clients/python")
    code = "import importlib.metadata as m, hypnerf_client as h; print(h.__file__); print(m.version('hypnerf-client') == h.__version__)"
    shown = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, check=True).stdout.split()
    assert Path(shown[0]).is_relative_to(SDK) and shown[1] == "True"


def test_the_sdk_imports_neither_torch_nor_the_project(tmp_path):
    code = "import sys, hypnerf_client; print(sorted({m.split('.')[0] for m in sys.modules} & {'torch', 'numpy', 'model', 'service'}))"
    done = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=_sdk_env("http://127.0.0.1:1"), capture_output=True, text=True,
                          check=True)
    assert done.stdout.strip() == "[]"


# -- service, model, instances ------------------------------------------------------------------------


def test_service_model_and_instances(client):
    assert client.health().status == "ok"
    ready = client.ready()
    info = client.model()
    assert ready.status == "ready" and ready.bundle == info.bundle.digest and info.bundle.components == ["hypernet"]
    assert info.codes.shape == 16 and info.limits.max_render_side == 256 and info.text_to_nerf is False
    assert client.cache().memory_budget_bytes > 0 and "hypnerf_cache_lookups_total" in client.metrics()
    page = client.instances.list(limit=4)
    assert page.total == 6 and len(page.items) == 4 and page.next is not None
    everything = list(client.instances.iter_all(page_size=4))
    assert [i.index for i in everything] == list(range(6)) and everything[:4] == page.items
    one = client.instances.get(everything[5])
    assert one == everything[5] and one.caption and one.attribution.source == "synth"


def test_the_api_key_is_sent_and_required(server, client):
    with Client(server.url, api_key="") as anonymous:
        assert anonymous.health().status == "ok"  # health stays open
        with pytest.raises(AuthenticationError) as caught:
            anonymous.model()
    assert caught.value.status == 401 and "Bearer" in caught.value.detail and caught.value.type == "urn:hypnerf:problem:unauthorized"


# -- NeRFs ---------------------------------------------------------------------------------------------


def test_nerfs_from_every_source(client):
    first, last = client.instances.list(limit=6).items[::5]
    nerf = client.nerfs.create(instance=first)
    assert nerf.codes is not None and len(nerf.codes.shape) == 16 and nerf.links.render.endswith("/render")
    assert client.nerfs.get(nerf) == nerf.model_copy(update={"cached": True})
    assert client.nerfs.create(codes=(nerf.codes.shape, nerf.codes.color)).id == nerf.id
    assert client.nerfs.create(codes=nerf.codes).cached
    assert client.nerfs.create(interpolate={"a": first.id, "b": last.id, "t": 0.0}).id == nerf.id
    mixed = client.nerfs.create(mix=(first.id, last.id))
    assert mixed.source == {"mix": {"shape": first.id, "color": last.id}} and mixed.id != nerf.id
    with pytest.raises(TypeError, match="exactly one"):
        client.nerfs.create(instance=first.id, mix=(first.id, last.id))


def test_renders_turntables_and_meshes(client, tmp_path):
    nerf = client.nerfs.create(instance=client.instances.list(limit=1).items[0].id)
    orbit = _pixels(client.nerfs.render(nerf, azimuth=60, elevation=30, radius=2.0, fov=50, width=48, height=32))
    assert orbit.shape == (32, 48, 3) and orbit.std() > 1.0
    pose = look_at(2.0 * spherical_direction(30, 60))  # the same camera as a 4x4 matrix (numpy)
    posed = _pixels(client.nerfs.render(nerf, pose=pose, fov=50, width=48, height=32))
    assert np.abs(posed.astype(int) - orbit.astype(int)).max() <= 1
    clear = _pixels(client.nerfs.save_render(nerf, tmp_path / "clear.png", width=24, height=24, background="transparent").read_bytes())
    assert clear.shape == (24, 24, 4) and clear[..., 3].min() < 10
    assert _pixels(client.nerfs.render(nerf, width=16, height=16, background=(0, 0, 0)))[0, 0].max() < 10
    assert np.array_equal(_pixels(client.nerfs.render(nerf, width=16, height=16, background="#000000")),
                          _pixels(client.nerfs.render(nerf, width=16, height=16, background="000000")))
    gif = Image.open(client.nerfs.save_turntable(nerf, tmp_path / "turn.gif", frames=3, width=16, height=16))
    assert gif.format == "GIF" and gif.n_frames == 3 and len(client.nerfs.turntable(nerf, frames=2, width=8, height=8)) > 0
    assert client.nerfs.mesh(nerf, format="glb", resolution=32)[:4] == b"glTF"
    assert client.nerfs.save_mesh(nerf, tmp_path / "chair.ply", resolution=32).read_bytes()[:3] == b"ply"
    assert b"\nf " in client.nerfs.save_mesh(nerf, tmp_path / "chair.obj", resolution=32, target_faces=100).read_bytes()
    with pytest.raises(TypeError, match="widht"):
        client.nerfs.render(nerf, widht=10)
    with pytest.raises(ValueError, match="16 numbers"):
        client.nerfs.render(nerf, pose=np.eye(3))
    with pytest.raises(ValueError, match="suffix|format"):
        client.nerfs.save_mesh(nerf, tmp_path / "chair.stl")


def test_text_and_retrieval_say_the_bundle_has_no_query_network(client, views):
    for ask in (lambda: client.text_to_nerf("a red chair"), lambda: client.retrieve(views[0][0], k=2)):
        with pytest.raises(NotImplementedByServerError) as caught:
            ask()
        assert caught.value.status == 501 and "query network" in caught.value.detail and isinstance(caught.value, APIError)


# -- errors -----------------------------------------------------------------------------------------------


def test_problems_map_to_the_error_hierarchy(client, views):
    images, poses = views
    cases = [
        (NotFoundError, 404, lambda: client.nerfs.get("f" * 64)),
        (NotFoundError, 404, lambda: client.instances.get("no-such-instance")),
        (NotFoundError, 404, lambda: client.jobs.get("0" * 32)),
        (ValidationError, 422, lambda: client.nerfs.render("f" * 64, width=257)),
        (ValidationError, 422, lambda: client.nerfs.create(codes={"shape": [0.0] * 15, "color": [0.0] * 16})),
        (ValidationError, 422, lambda: client.nerfs.create(instance="no-such-instance")),
        (PayloadTooLargeError, 413, lambda: client.jobs.create_inversion([os.urandom(320_000), images[1]], poses=poses)),
        (UnsupportedMediaError, 415, lambda: client.jobs.create_inversion([b"plain text, not a picture", images[1]], poses=poses)),
        (ValidationError, 422, lambda: client.jobs.create_inversion(images)),  # two images without poses: the search takes one
    ]
    for cls, status, call in cases:
        with pytest.raises(cls) as caught:
            call()
        error = caught.value
        assert isinstance(error, APIError) and isinstance(error, HypnerfError) and error.status == status, (cls, error)
        assert error.title and error.detail and error.problem["status"] == status and error.type.startswith("urn:hypnerf:problem:")
    with pytest.raises(ValidationError) as caught:
        client.nerfs.render("f" * 64, width=257)
    assert [(e.field, e.loc) for e in caught.value.errors] == [("width", ["query", "width"])] and "256" in str(caught.value)


class Forwarder:
    """A loopback TCP forwarder to the server, opened on a port that refuses connections until ``open()``."""

    def __init__(self, target_port: int):
        self.port = free_port()
        self.target = target_port
        self.listener: socketserver.ThreadingTCPServer | None = None
        self.opened_at: float | None = None

    def open(self) -> None:
        target = self.target

        class Pipe(socketserver.BaseRequestHandler):
            def handle(self):
                with socket.create_connection(("127.0.0.1", target)) as upstream:
                    back = threading.Thread(target=_pump, args=(upstream, self.request), daemon=True)
                    back.start()
                    _pump(self.request, upstream)
                    back.join()

        socketserver.ThreadingTCPServer.allow_reuse_address = True
        # taken before the port is bound: a connection can succeed from the bind on, so any answered
        # attempt comes after this instant
        self.opened_at = time.monotonic()
        self.listener = socketserver.ThreadingTCPServer(("127.0.0.1", self.port), Pipe)
        self.listener.daemon_threads = True
        threading.Thread(target=self.listener.serve_forever, daemon=True).start()

    def close(self) -> None:
        if self.listener is not None:
            self.listener.shutdown()
            self.listener.server_close()


def _pump(source: socket.socket, sink: socket.socket) -> None:
    try:
        while data := source.recv(65536):
            sink.sendall(data)
        sink.shutdown(socket.SHUT_WR)
    except OSError:
        pass


def test_refused_connections_are_retried_until_the_server_answers(server):
    forwarder = Forwarder(server.port)
    url = f"http://127.0.0.1:{forwarder.port}"
    with Client(url, api_key=KEY, max_retries=0) as impatient, pytest.raises(hypnerf_client.ConnectionError, match="refused"):
        impatient.health()
    attempts, answered = [], []
    opening = threading.Timer(0.6, forwarder.open)
    opening.start()
    try:
        hooks = {"request": [lambda request: attempts.append(time.monotonic())], "response": [lambda response: answered.append(time.monotonic())]}
        with httpx.Client(event_hooks=hooks) as http, Client(url, api_key=KEY, max_retries=6, backoff=0.2, http_client=http) as patient:
            assert patient.model().instances == 6
        # refused before the port opened, retried, and answered once, after it opened (a request hook
        # fires before its connection, so the answered attempt may have started just before the bind)
        assert len(attempts) >= 2 and len(answered) == 1 and attempts[0] < forwarder.opened_at < answered[0]
    finally:
        opening.join()
        forwarder.close()


# -- async -------------------------------------------------------------------------------------------------


def test_the_async_client_matches_the_sync_one(server, client):
    async def scenario():
        async with AsyncClient(server.url, api_key=KEY) as sdk:
            info = await sdk.model()
            instances = [i async for i in sdk.instances.iter_all(page_size=5)]
            nerfs = await asyncio.gather(*(sdk.nerfs.create(instance=i) for i in instances[:2]))
            png = await sdk.nerfs.render(nerfs[0], width=24, height=24)
            jobs = await sdk.jobs.list(limit=5)
            with pytest.raises(NotFoundError):
                await sdk.nerfs.get("e" * 64)
            return info, instances, nerfs, png, jobs

    info, instances, nerfs, png, jobs = asyncio.run(scenario())
    assert info == client.model() and instances == list(client.instances.iter_all())
    assert [n.id for n in nerfs] == [client.nerfs.create(instance=i).id for i in instances[:2]]
    assert np.array_equal(_pixels(png), _pixels(client.nerfs.render(nerfs[0], width=24, height=24)))
    assert [j.id for j in jobs.items] == [j.id for j in client.jobs.list(limit=5).items]


# -- inversion jobs ---------------------------------------------------------------------------------------


def test_an_inversion_job_waited_for_with_progress(client, views):
    images, poses = views
    seen = []
    # long enough (seconds even on an idle machine) for progress, stored every 0.5 s, to be seen twice
    steady = InversionOptions(steps=80, rays_per_step=512, init="mean")
    job = client.jobs.create_inversion(images, poses=poses, options=steady, idempotency_key="sdk-wait-1")
    assert job.status == "queued" and job.links.self == f"/v1/jobs/{job.id}"
    done = client.jobs.wait(job, timeout=120, poll_interval=0.1, on_progress=seen.append)
    assert done.status == "succeeded" and done.done and seen[-1] == done
    steps = [j.progress.step for j in seen if j.progress]
    assert len(steps) >= 2 and steps == sorted(steps) and steps[-1] <= steady.steps
    assert done.result is not None and np.isfinite(done.result.psnr)
    assert _pixels(client.nerfs.render(done.result, width=16, height=16)).std() > 0
    assert client.nerfs.get(done.result).source["inversion"] == job.id
    # the same key and request: the same job; the same key and another request: 409
    assert client.jobs.create_inversion(images, poses=poses, options=steady, idempotency_key="sdk-wait-1").id == job.id
    with pytest.raises(ConflictError):
        client.jobs.create_inversion(images, poses=poses, options={**QUICK.model_dump(), "seed": 3}, idempotency_key="sdk-wait-1")
    with pytest.raises(ConflictError, match="already succeeded"):
        client.jobs.cancel(job)
    assert job.id in [j.id for j in client.jobs.list(status="succeeded").items]
    assert job.id in [j.id for j in client.jobs.iter_all(status="succeeded", page_size=1)]
    assert [(e.event, e.job.status) for e in client.jobs.events(job)] == [("job", "succeeded")]


def test_job_events_stream_until_the_job_finishes(client, views):
    images, poses = views
    job = client.jobs.create_inversion([p.read_bytes() for p in images], poses=[p.tolist() for p in poses], options=QUICK)
    events = list(client.jobs.events(job.id))
    order = ["queued", "running", "succeeded"]
    statuses = [order.index(e.job.status) for e in events]
    assert all(e.event == "job" for e in events) and statuses[-1] == 2 and statuses == sorted(statuses)
    assert len(events) >= 2 and [e.id for e in events] == [str(n) for n in range(1, len(events) + 1)]  # seen live, in order
    steps = [e.job.progress.step for e in events if e.job.progress]
    assert steps == sorted(steps) and events[-1].job.result is not None


def test_a_full_queue_is_retried_after_retry_after_and_cancel_stops_a_job(server, client, views):
    images, poses = views
    running = client.jobs.create_inversion(images, poses=poses, options=LONG)
    _until(lambda: client.jobs.get(running).progress is not None)
    with pytest.raises(JobTimeoutError) as late:
        client.jobs.wait(running, timeout=0.2, poll_interval=0.05)
    assert late.value.job.status == "running" and "still running" in str(late.value)
    with pytest.raises(RateLimitError) as refused:
        client.with_options(max_retries=0).jobs.create_inversion(images, poses=poses, options=QUICK)
    retry_after = refused.value.retry_after
    assert refused.value.status == 429 and retry_after >= 1

    answers = []

    def record(response: httpx.Response) -> None:
        answers.append((response.status_code, time.monotonic(), response.headers.get("retry-after")))
        if response.status_code == 429 and len(answers) == 1:
            client.jobs.cancel(running)  # room in the queue well before the Retry-After passes

    with httpx.Client(event_hooks={"response": [record]}) as http, Client(server.url, api_key=KEY, max_retries=3, http_client=http) as patient:
        queued = patient.jobs.create_inversion(images, poses=poses, options=QUICK)
    assert answers[0][0] == 429 and answers[-1][0] == 202
    for (_, asked_at, wait), (_, retried_at, _) in itertools.pairwise(answers):
        assert retried_at - asked_at >= float(wait)  # each retry waited as long as the server asked
    with pytest.raises(JobCanceledError) as canceled:
        client.jobs.wait(running, timeout=60)
    assert canceled.value.job.status == "canceled" and canceled.value.job.result is None
    assert client.jobs.cancel(running).status == "canceled"  # canceling again is a no-op
    assert client.jobs.wait(queued, timeout=120).status == "succeeded"


# -- the README ---------------------------------------------------------------------------------------------


def readme_examples() -> list[str]:
    return re.findall(r"```python\n(.*?)```", (SDK / "README.md").read_text(), flags=re.DOTALL)


def test_the_readme_examples_run_as_written(server, tmp_path):
    examples = readme_examples()
    assert len(examples) >= 6
    printed = []
    for number, code in enumerate(examples):
        folder = tmp_path / f"example{number}"
        folder.mkdir()
        done = subprocess.run([sys.executable, "-c", code], cwd=folder, env=_sdk_env(server.url), capture_output=True, text=True,
                              timeout=180, check=False)
        assert done.returncode == 0, f"README example {number} failed:\n{code}\n{done.stdout}\n{done.stderr}"
        printed.append(done.stdout)
    first = tmp_path / "example0"
    assert _pixels((first / "chair.png").read_bytes()).shape == (256, 256, 3) and (first / "chair.glb").read_bytes()[:4] == b"glTF"
    assert "not served by this bundle" in printed[2] and "inverted into NeRF" in printed[3]


# -- pieces on their own ---------------------------------------------------------------------------------------


def test_the_retry_policy():
    policy = RetryPolicy(max_retries=2, backoff=0.5, max_backoff=8.0, max_retry_after=60.0)
    assert 0.375 <= policy.wait(0) <= 0.5 and 0.75 <= policy.wait(1) <= 1.0 and policy.wait(10) <= 8.0
    assert 3.0 <= policy.wait(0, retry_after=3.0) <= 3.3
    headers = {"retry-after": "2"}
    assert 2.0 <= policy.after_status(0, 429, headers, idempotent=True) <= 2.2
    assert policy.after_status(0, 429, headers, idempotent=False) is None  # not safe to repeat
    assert policy.after_status(2, 503, headers, idempotent=True) is None  # retries used up
    assert policy.after_status(0, 500, {}, idempotent=True) is None and policy.after_status(0, 404, {}, idempotent=True) is None
    assert policy.after_status(0, 503, {"retry-after": "120"}, idempotent=True) is None  # too long to wait for
    refused = httpx.ConnectError("refused")
    assert policy.after_transport(0, refused, idempotent=False) is not None  # never sent: safe for any call
    assert policy.after_transport(0, httpx.ReadTimeout("slow"), idempotent=False) is None
    assert policy.after_transport(0, httpx.ReadTimeout("slow"), idempotent=True) is not None
    later = email.utils.formatdate(time.time() + 30, usegmt=True)
    assert 28 <= retry_after_seconds({"retry-after": later}) <= 31
    assert retry_after_seconds({"retry-after": "soon"}) is None and retry_after_seconds({}) is None
    with pytest.raises(ValueError, match="max_retries"):
        RetryPolicy(max_retries=-1)


def test_the_event_stream_decoder():
    decoder = SSEDecoder()
    lines = [": keep-alive", "", "id: 1", "event: job", "data: {\"a\":", "data: 1}", "", "data:plain", ""]
    events = [event for event in map(decoder.decode, lines) if event is not None]
    # the last event id carries over to later events (WHATWG), data lines join with newlines
    assert [(e.id, e.event, e.data) for e in events] == [("1", "job", "{\"a\":\n1}"), ("1", "message", "plain")]


def _job(status: str, **fields) -> Job:
    base = {"id": "j1", "kind": "inversion", "status": status, "created_at": "2025-01-01T00:00:00Z", "attempts": 1, "max_attempts": 3,
            "cancel_requested": False, "links": {"self": "/v1/jobs/j1", "events": "/v1/jobs/j1/events", "cancel": "/v1/jobs/j1/cancel"}}
    return Job.model_validate({**base, **fields})


def test_waiting_reports_changes_once_and_raises_on_failure():
    seen = []
    watch = JobWatch("j1", timeout=None, poll_interval=0.1, on_progress=seen.append)
    assert not watch.finished(_job("queued")) and not watch.finished(_job("queued"))
    assert not watch.finished(_job("running", progress={"step": 1, "steps": 4}))
    with pytest.raises(JobFailedError, match="Optimisation diverged: the loss became NaN") as failed:
        watch.finished(_job("failed", error={"title": "Optimisation diverged", "detail": "the loss became NaN"}))
    assert [j.status for j in seen] == ["queued", "running", "failed"] and failed.value.job.error.title == "Optimisation diverged"
    with pytest.raises(ValueError, match="poll_interval"):
        JobWatch("j1", timeout=None, poll_interval=0, on_progress=None)
