"""What a worker process runs: an inversion job (test-time optimisation, optionally denoise and
finetune) and a webhook delivery.

The bundle is loaded once per worker process (``WorkerContext.bundle``, warmed when the process
starts) and its torch hypernetwork built once. A job is claimed (queued -> running under this
process's lease), run with the lease's heartbeat, and finished with one write that succeeds only
while the lease is held; the resulting NeRF is put into the shared disk NeRF cache first, under
its content address, so the API process finds it when a client renders it.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
import uuid
from datetime import UTC, datetime

import torch

from model.bundle import Bundle, BundleError, load_bundle
from model.denoise.finetune import DenoiseConfig, denoise_and_finetune, ring_poses
from model.denoise.io import load_denoiser
from model.nerf.config import from_dict
from model.optimize.tto import TTOConfig, TTOError, invert
from model.prior.codes import generated_grid
from service.cache import NerfCache, NerfEntry, params_nerf_id
from service.jobs.backends import open_blobs, open_store
from service.jobs.blobs import MissingBlob
from service.jobs.inputs import load_views
from service.jobs.lease import Lease
from service.jobs.records import CANCELED, FAILED, SUCCEEDED, Job, failure
from service.jobs.webhooks import deliver
from service.schemas.jobs import JobView
from service.settings import Settings

log = logging.getLogger(__name__)


class WorkerContext:
    """What one worker process opens once: the store, the input blobs, the NeRF cache, the bundle.

    Built lazily and per process (a forked worker never reuses its parent's connections)."""

    def __init__(self, settings: Settings):
        self.settings = settings
        self._pid: int | None = None
        self._lock = threading.Lock()
        self._bundle: Bundle | None = None
        self._denoiser = None

    def _opened(self) -> None:
        if self._pid != os.getpid():
            self.store = open_store(self.settings)
            self.blobs = open_blobs(self.settings)
            self.cache = NerfCache(self.settings.nerf_cache_dir, memory_bytes=0, disk_bytes=self.settings.cache_disk_bytes)
            self.owner = f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:6]}"
            self._bundle = self._denoiser = None
            self._pid = os.getpid()

    def open(self) -> WorkerContext:
        with self._lock:
            self._opened()
        return self

    def bundle(self) -> Bundle:
        """The bundle, loaded (and verified) on first use in this process."""
        with self._lock:
            self._opened()
            if self._bundle is None:
                start = time.perf_counter()
                bundle = load_bundle(self.settings.bundle, verify=self.settings.verify_bundle)
                net = bundle.hypernet()
                with torch.no_grad():  # the first density evaluation loads the fused hash-grid kernel: pay it now, not in a job
                    params = net.params_from_codes(*net.codes(torch.zeros(1, dtype=torch.long)))
                    generated_grid(params, bundle.field, bundle.scene, resolution=8)
                self._bundle = bundle
                log.info("worker %s loaded bundle %s in %.1f s", self.owner, self._bundle.digest[:12], time.perf_counter() - start)
            return self._bundle

    def denoiser(self):
        bundle = self.bundle()
        with self._lock:
            if self._denoiser is None:
                self._denoiser, _ = load_denoiser(bundle.denoiser_path.parent)
            return self._denoiser

    def warm_up(self) -> None:
        """Called when a worker process starts: share the cores between workers (or use
        ``torch_threads``), load the bundle."""
        torch.set_num_threads(self.settings.torch_threads or max(1, (os.cpu_count() or 1) // max(1, self.settings.workers)))
        try:
            self.bundle()
        except (BundleError, OSError) as exc:  # each job reports it again, as its error
            log.error("worker could not load the bundle %s: %s", self.settings.bundle, exc)


class _Progress:
    """Turns the optimisation's reports into the job's progress (steps over all phases, ETA)."""

    def __init__(self, lease: Lease, total: int):
        self.lease, self.total, self.offset = lease, total, 0
        self.started = time.perf_counter()

    def __call__(self, report: dict, phase: str | None = None) -> None:
        done = self.offset + report["step"] + 1
        rate = (time.perf_counter() - self.started) / done
        self.lease.report({"step": done, "steps": self.total, "phase": phase or report.get("phase"), "loss": report.get("loss"),
                           "psnr": report.get("psnr"), "eta_s": round(rate * max(self.total - done, 0), 2)})


def _result(job: Job, context: WorkerContext, lease: Lease) -> tuple[str, dict | None, dict | None]:
    """Run the job: ``(final status, result, error)``."""
    bundle = context.bundle()
    request = job.request
    if request["bundle"] != bundle.digest:
        return FAILED, None, failure("Bundle changed", f"the job was submitted for bundle {request['bundle'][:12]} but this worker "
                                     f"serves {bundle.digest[:12]}; submit it again")
    images, c2w, cameras = load_views(request, context.blobs)
    cfg = from_dict(TTOConfig, request["tto"])
    denoise = from_dict(DenoiseConfig, request["denoise"]) if request["denoise"] else None
    progress = _Progress(lease, cfg.steps + cfg.finetune_steps + (denoise.total_steps if denoise else 0))
    inverted = invert(bundle.hypernet(), bundle.scene, images, c2w, cameras, cfg, progress=progress, should_stop=lease.should_stop)
    if lease.should_stop():
        return CANCELED, None, None
    params, grid, finetuned = inverted.params, inverted.grid, cfg.finetune_steps > 0
    steps = inverted.history[-1]["step"] + 1 if inverted.history else 0
    psnr = inverted.history[-1]["psnr"] if inverted.history else None
    if denoise is not None:
        progress.offset = progress.total - denoise.total_steps
        tuned = denoise_and_finetune(params, bundle.field, bundle.scene, context.denoiser(), ring_poses(), bundle.camera, denoise, grid=grid,
                                     inputs=(images, inverted.c2w, cameras), progress=lambda report: progress(report, "denoise"))
        if lease.should_stop():
            return CANCELED, None, None
        params, grid, finetuned = tuned.params, tuned.grid, True
        steps += denoise.total_steps
    nerf_id = params_nerf_id(bundle.digest, params)
    codes = {"shape": inverted.shape_code.tolist(), "color": inverted.color_code.tolist()}
    meta = {"source": {"inversion": job.id, "finetuned": finetuned}, "bundle": bundle.digest,
            "created_at": datetime.now(UTC).isoformat(timespec="seconds")}
    if not finetuned:
        meta["codes"] = codes  # the codes reproduce this NeRF only when it was not finetuned
    context.cache.put(nerf_id, NerfEntry(params, grid, meta))
    return SUCCEEDED, {"nerf_id": nerf_id, "codes": codes, "finetuned": finetuned, "psnr": psnr, "steps": steps,
                       "init": inverted.init, "wall_s": round(inverted.wall_s, 3)}, None


def run_inversion(context: WorkerContext, job_id: str, notify) -> None:
    """Claim the job, run it under a lease, finish it (only while the lease is held), then call
    ``notify(job_id)`` if it has a webhook. Interrupted (the worker is stopping), the job goes back
    to the queue."""
    context.open()
    store, owner, lease_s = context.store, context.owner, context.settings.job_lease_s
    job = store.claim(job_id, owner, lease_s)
    if job is None:
        log.info("job %s is no longer queued (canceled, finished or taken by another worker); skipping", job_id)
        return
    log.info("job %s: attempt %d of %d on %s", job_id, job.attempts, job.max_attempts, owner)
    lease = Lease(store, job_id, owner, lease_s).start()
    try:
        status, result, error = _result(job, context, lease)
    except KeyboardInterrupt:
        lease.stop()
        if store.release(job_id, owner):
            log.info("job %s: interrupted; back in the queue", job_id)
        raise
    except (TTOError, MissingBlob, BundleError, ValueError) as exc:
        status, result, error = FAILED, None, failure("Inversion failed", str(exc))
    except Exception as exc:
        log.exception("job %s failed", job_id)
        status, result, error = FAILED, None, failure("Inversion failed", f"unexpected {type(exc).__name__}: {exc}")
    finally:
        lease.stop()
    if lease.lost:
        return
    if store.finish(job_id, owner, status, result=result, error=error):
        log.info("job %s: %s", job_id, status)
        if job.webhook:
            notify(job_id)
    else:
        log.warning("job %s: lease lost before finishing; the result of this run is discarded", job_id)


def run_webhook(context: WorkerContext, job_id: str) -> None:
    """POST the finished job to its webhook and record the outcome."""
    context.open()
    job = context.store.get(job_id)
    if job is None or not job.webhook or not job.finished:
        return
    secret = context.settings.webhook_secret
    if secret is None:
        context.store.record_webhook(job_id, {"delivered": False, "error": "this worker has no HYPNERF_WEBHOOK_SECRET to sign with"})
        return
    body = JobView.of(job).model_dump_json().encode()
    outcome = deliver(job.webhook["url"], body, secret.get_secret_value(), f"job.{job.status}")
    context.store.record_webhook(job_id, outcome)
