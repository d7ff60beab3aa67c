"""Short core calls that would freeze Blender (*Check*, *Add Region Box*, *Show Tiles*): the core's answer is awaited on a
thread and what it means for the scene is done on the main thread by a timer.

Blender data may only be touched on the main thread, so a task is split in three: the caller reads the scene and
starts the task, `work` (no Blender data) runs on a thread, and `finish(result)` (main thread) adds what the answer
says and returns the line reported in the Info log. In background runs (batch, tests) timers never fire: callers
there run synchronously, or call `poll` in a loop.
"""
from __future__ import annotations

import threading
from typing import Any, Callable

import bpy

from . import messages

TASKS: dict[str, dict[str, Any]] = {}
POLL_S = 0.2


def busy(key: str) -> bool:
    task = TASKS.get(key)
    return task is not None and task["thread"].is_alive()


def start(key: str, label: str, work: Callable[[], Any], finish: Callable[[Any], str],
          on_error: Callable[[Exception], None] | None = None, undo: bool = True) -> None:
    """Run `work()` on a thread under `key` (one at a time per key) and `finish(its result)` later on the main
    thread (a timer in the interface, `poll(key)` elsewhere); `on_error(exc)` there too when either raised.
    `undo`: the finished task is an undo step (it changed the scene). Returns at once."""
    if busy(key):
        raise RuntimeError(f"{label} is still running")
    task: dict[str, Any] = {"label": label, "finish": finish, "on_error": on_error, "undo": undo}

    def run() -> None:
        try:
            task["result"] = work()
        except Exception as exc:  # noqa: BLE001  (reported on the main thread)
            task["error"] = exc

    task["thread"] = threading.Thread(target=run, name=f"hgca-{key}", daemon=True)
    TASKS[key] = task
    task["thread"].start()
    if not bpy.app.background:
        bpy.app.timers.register(lambda: None if poll(key) is not None else POLL_S, first_interval=POLL_S)


def poll(key: str) -> str | None:
    """The reported line once the task under `key` has ended (its `finish` run, or its error reported), else None;
    main thread."""
    task = TASKS.get(key)
    if task is None or task["thread"].is_alive():
        return None
    del TASKS[key]
    try:
        if "error" in task:
            raise task["error"]
        text = task["finish"](task["result"])
    except Exception as exc:  # noqa: BLE001
        if task["on_error"] is not None:
            task["on_error"](exc)
        text = f"{task['label']} failed: {exc}"
        messages.report("ERROR", text)
        return text
    messages.report("INFO", text)
    if task["undo"] and not bpy.app.background:
        try:
            bpy.ops.ed.undo_push(message=task["label"])
        except RuntimeError:
            pass
    return text
