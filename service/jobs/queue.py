"""The huey queue of the job system: the tasks registered on it and how jobs are enqueued.

huey carries only a job's id; the job itself is in the jobs table. A message can therefore be
delivered twice (a re-queue races a slow worker) without harm: a worker that cannot claim the job
(it is no longer queued) does nothing. The same registration runs in API processes (to enqueue)
and in worker processes (to execute), so both agree on the task names.
"""

from __future__ import annotations

from service.jobs.backends import open_huey
from service.jobs.tasks import WorkerContext, run_inversion, run_webhook
from service.settings import Settings

INVERSION_TASK = "inversion"
WEBHOOK_TASK = "webhook"


class JobQueue:
    """huey with the job system's tasks; ``context`` is what executing them opens (lazily)."""

    def __init__(self, settings: Settings):
        self.huey = open_huey(settings)
        self.context = WorkerContext(settings)
        self._inversion = self.huey.task(name=INVERSION_TASK)(self._run_inversion)
        self._webhook = self.huey.task(name=WEBHOOK_TASK)(self._run_webhook)
        self.huey.on_startup("load-bundle")(self.context.warm_up)

    def _run_inversion(self, job_id: str) -> None:
        run_inversion(self.context, job_id, notify=self.enqueue_webhook)

    def _run_webhook(self, job_id: str) -> None:
        run_webhook(self.context, job_id)

    def enqueue_inversion(self, job_id: str) -> None:
        self._inversion(job_id)

    def enqueue_webhook(self, job_id: str) -> None:
        self._webhook(job_id)

    def pending_inversions(self) -> set[str]:
        """Ids of the jobs with an inversion message waiting in the queue."""
        return {task.args[0] for task in self.huey.pending() if task.name == INVERSION_TASK and task.args}
