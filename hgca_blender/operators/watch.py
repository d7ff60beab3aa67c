"""Watching a scene's job from the operator that started it: Esc cancels it, the status bar shows how far it is.

Complete, Complete Along Drive and Estimate Poses all start a job in the background (`execute`) and return; from
the panel (`invoke`) they then stay as a modal handler until the job ends, so the job can be stopped with Esc
wherever the mouse is and its progress shows in the status bar. The operators differ only in what the status bar
shows and what the cancel reports, the two hooks of `JobWatching`.
"""
from __future__ import annotations

from typing import Callable, Union

import bpy

from ..jobs import completion
from ..jobs.core import Job

# What the status bar shows: a line of text, or a header draw function (`WorkSpace.status_text_set` takes both)
StatusText = Union[str, Callable[[bpy.types.Header, bpy.types.Context], None]]


def job_line(job: Job) -> str:
    """The status bar's line for a job: its status and share done (and time left), or only its status while the
    results go in slice by slice ("Adding sample 2 of 3: 45 %")."""
    if job.finishing is not None:
        return f"hGCA: {job.status}  Esc: cancel"
    return f"hGCA: {job.status} ({job.progress * 100:.0f}%{completion.time_left(job)})  Esc: cancel"


class JobWatching:
    """Mixin for an operator whose `execute` starts its scene's job: `invoke` starts it and watches it (`modal`).

    Hooks: `cancel_message`, reported when Esc cancels the job, and `status_text(job)`, what the status bar shows
    while it runs (asked at every event the operator sees, so it follows the job)."""

    cancel_message = "hGCA job cancelled (Esc)"
    _timer = None

    @staticmethod
    def status_text(job: Job) -> StatusText:
        return job_line(job)

    def invoke(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        """From the panel: start the job, then watch it so Esc cancels it and the status bar shows it."""
        if self.execute(context) != {"FINISHED"}:
            return {"CANCELLED"}
        if context.window is None:
            return {"FINISHED"}
        job = completion.ACTIVE.get(context.scene.name)
        if job is not None:
            completion.status_bar(context, self.status_text(job))
        self._timer = context.window_manager.event_timer_add(completion.POLL_INTERVAL_S, window=context.window)
        context.window_manager.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        job = completion.ACTIVE.get(context.scene.name)
        if job is not None and job.running and event.type == "ESC" and event.value == "PRESS":
            job.cancel()
            completion.poll_all()
            self.report({"INFO"}, self.cancel_message)
            return self._finish(context)
        if job is None or not job.running:
            return self._finish(context)
        completion.status_bar(context, self.status_text(job))
        for area in context.screen.areas if context.screen is not None else []:
            if area.type == "STATUSBAR":    # a drawn status (a progress bar) follows the job too
                area.tag_redraw()
        return {"PASS_THROUGH"}

    def _finish(self, context: bpy.types.Context) -> set[str]:
        if self._timer is not None:
            context.window_manager.event_timer_remove(self._timer)
            self._timer = None
        completion.status_bar(context, None)
        return {"FINISHED"}
