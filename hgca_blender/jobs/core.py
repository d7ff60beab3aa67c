"""Running hgca_core as a subprocess: one-shot commands (`run_core`) and long jobs speaking `--progress jsonl`.

The add-on never imports torch or hgca_core: everything the model does happens in
`<python> -m hgca_core.cli ...`, with arrays passed as .npz files. A `Job` owns a temporary folder, a
`subprocess.Popen` and two reader threads; the stdout thread parses the progress records into a queue, and
`poll_once()` (main thread) handles them. Nothing here touches Blender data, so what a job means (a
completion and its meshes) lives in a subclass (`jobs.CompletionJob`).

The add-on and the core's Python may come from different hgca versions, so every progress record carries
the protocol version (docs/CONTRACTS.md, "Progress records"); a job whose core speaks another one stops at
its first record with a message that says so, rather than misreading it.
"""
from __future__ import annotations

import json
import os
import queue
import re
import shutil
import signal
import subprocess
import tempfile
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any, Callable

CORE_MODULE = "hgca_core.cli"
PROGRESS_PROTOCOL = 1  # must equal hgca_core.progress.PROTOCOL (tests/test_complete.py holds them equal)
KILL_GRACE_S = 3.0
# `hgca complete: warning: ...` (hgca_core.cli prints its own warnings on one stderr line each)
WARNING_LINE = re.compile(r"^hgca [\w-]+: warning: (.+)$")


class CoreError(RuntimeError):
    """The core could not be run or reported an error; the message is meant for the user."""


def core_command(python: str, args: list[str]) -> list[str]:
    """`<python> -m hgca_core.cli ARGS`: the only way the add-on reaches the core."""
    return [python, "-m", CORE_MODULE, *[str(a) for a in args]]


def _child_env() -> dict[str, str]:
    """Environment for the core: unbuffered so progress lines arrive as they are printed."""
    env = dict(os.environ)
    env["PYTHONUNBUFFERED"] = "1"
    return env


def _group_kwargs() -> dict[str, Any]:
    """Start the core in its own process group so cancel can stop it and any children it spawned."""
    if os.name == "nt":
        return {"creationflags": subprocess.CREATE_NEW_PROCESS_GROUP}
    return {"start_new_session": True}


def check_python(python: str) -> None:
    if not python:
        raise CoreError("No Python interpreter for hgca_core is set: choose one in the hGCA add-on preferences")
    if not Path(python).is_file():
        raise CoreError(f"Python interpreter not found: {python} (set it in the hGCA add-on preferences)")


def error_message(stderr: str, returncode: int | None, python: str = "") -> str:
    """The most useful line of a failed run: the core's 'error:' line, else the last line printed."""
    lines = [ln.strip() for ln in stderr.splitlines() if ln.strip()]
    if any("No module named" in ln and "hgca_core" in ln for ln in lines):
        return (f"hgca_core is not installed for {python or 'this interpreter'}: "
                "set the core's Python in the hGCA add-on preferences")
    missing = [ln for ln in lines if "No module named" in ln]
    if missing:  # hgca_core is there but its dependencies are not (a PYTHONPATH pointing at a checkout)
        return (f"{python or 'this interpreter'} cannot run hgca_core ({missing[-1]}): "
                "set the core's Python in the hGCA add-on preferences")
    if any("argument command: invalid choice" in ln for ln in lines):
        return (f"the hgca_core at {python or 'this interpreter'} lacks a command this add-on needs: "
                f"install the hgca version that matches the add-on ({lines[-1]})")
    for ln in reversed(lines):
        if "error:" in ln.lower():
            return ln
    if lines:
        return lines[-1]
    return f"hgca_core exited with status {returncode}"


def killed_message(signum: int) -> str:
    """What to tell a user whose core was ended from outside by a signal (the system's out-of-memory killer sends
    SIGKILL): which signal, and what to try; the core's own last line would only say what it was doing."""
    import signal

    try:
        name = signal.Signals(signum).name
    except ValueError:
        name = f"signal {signum}"
    if signum == getattr(signal, "SIGKILL", 9):
        return (f"the hgca core was killed ({name}), most likely by the system for lack of memory: try a smaller "
                "region, fewer samples or the coarse stage, or close other programs")
    return f"the hgca core was stopped from outside ({name}) before it finished: start the job again"


def run_core(python: str, args: list[str], timeout: float | None = None,
             cwd: str | Path | None = None) -> subprocess.CompletedProcess:
    """Run one core command to completion (`read`, `region`, `--version`); CoreError on failure.

    It runs in a temporary folder by default: `python -m` puts the working directory first on
    sys.path, and Blender's working directory must not decide which hgca_core gets imported.
    """
    check_python(python)
    try:
        proc = subprocess.run(core_command(python, args), capture_output=True, text=True, timeout=timeout,
                              stdin=subprocess.DEVNULL, env=_child_env(), cwd=str(cwd or tempfile.gettempdir()))
    except (OSError, subprocess.SubprocessError) as exc:
        raise CoreError(f"could not run {python}: {exc}") from exc
    if proc.returncode != 0:
        raise CoreError(error_message(proc.stderr, proc.returncode, python))
    return proc


def run_core_json(python: str, args: list[str], timeout: float | None = None,
                  cwd: str | Path | None = None) -> dict[str, Any]:
    """Run a core command that prints one JSON object (`hgca region --json`) and return that object."""
    proc = run_core(python, args, timeout=timeout, cwd=cwd)
    lines = [ln for ln in proc.stdout.splitlines() if ln.strip()]
    try:
        obj = json.loads(lines[-1]) if lines else None
    except ValueError:
        obj = None
    if not isinstance(obj, dict):
        raise CoreError(f"hgca {args[0]} printed no JSON object: {proc.stdout[-200:]!r}")
    return obj


def parse_progress_line(line: str) -> dict[str, Any]:
    """One stdout line -> event dict; lines that are not JSON objects become 'log' events."""
    text = line.strip()
    try:
        event = json.loads(text)
    except ValueError:
        return {"stage": "log", "message": text}
    if not isinstance(event, dict) or "stage" not in event:
        return {"stage": "log", "message": text}
    return event


def protocol_error(event: dict[str, Any], python: str) -> str:
    """Why a progress record cannot be read by this add-on, or "" when it speaks PROGRESS_PROTOCOL."""
    version = event.get("protocol")
    if version == PROGRESS_PROTOCOL:
        return ""
    where = f"the hgca_core at {python}" if python else "hgca_core"
    if version is None:
        return (f"{where} is older than this add-on (its progress records carry no protocol version; the add-on "
                f"reads protocol {PROGRESS_PROTOCOL}): install the hgca version that matches the add-on")
    return (f"{where} writes progress protocol {version}, this add-on reads protocol {PROGRESS_PROTOCOL}: "
            "install matching versions of the add-on and hgca")


def _terminate_tree(proc: subprocess.Popen) -> None:
    """Stop the process and everything in its group: SIGTERM, then SIGKILL after a grace period."""
    if proc.poll() is not None:
        return
    if os.name == "nt":
        subprocess.run(["taskkill", "/F", "/T", "/PID", str(proc.pid)], capture_output=True)
    else:
        try:
            os.killpg(proc.pid, signal.SIGTERM)
        except (ProcessLookupError, PermissionError):
            proc.terminate()
    try:
        proc.wait(timeout=KILL_GRACE_S)
        return
    except subprocess.TimeoutExpired:
        pass
    if os.name != "nt":
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            proc.kill()
    else:
        proc.kill()
    proc.wait(timeout=KILL_GRACE_S)


class Job:
    """A core subprocess speaking `--progress jsonl`, observed from the main thread via `poll_once()`.

    States: "running" -> "done" | "error" | "cancelled". The temporary folder is removed in every terminal
    state. Subclasses show progress records (`on_progress`), decide what success means (`on_success`) and
    where the state is shown (`publish`).
    """

    def __init__(self, cmd: list[str], workdir: Path) -> None:
        self.cmd = cmd
        self.workdir = Path(workdir)
        self.state = "running"
        self.progress = 0.0
        self.status = "Starting"
        self.error = ""
        self.outputs: list[Path] = []
        self.returncode: int | None = None
        self.started = time.monotonic()
        self._events: queue.Queue[dict[str, Any]] = queue.Queue()
        self._stderr: deque[str] = deque(maxlen=200)
        self.warnings: list[str] = []  # the core's warnings, in order (stderr; shown with the job's report)
        self._reported_error = ""
        self._ended = False
        self._done_event: dict[str, Any] | None = None
        self.finishing: Any = None   # what on_success returned: results going into the scene over the next polls
        try:
            self._proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                          stdin=subprocess.DEVNULL, text=True, errors="replace", bufsize=1,
                                          env=_child_env(), cwd=str(self.workdir), **_group_kwargs())
        except OSError as exc:
            self._cleanup()
            raise CoreError(f"could not start {cmd[0]}: {exc}") from exc
        self._err_thread = threading.Thread(target=self._read_stderr, name="hgca-stderr", daemon=True)
        self._out_thread = threading.Thread(target=self._read_stdout, name="hgca-stdout", daemon=True)
        self._err_thread.start()
        self._out_thread.start()

    # -- reader threads (never touch bpy) ---------------------------------------------------------
    def _read_stderr(self) -> None:
        assert self._proc.stderr is not None
        try:
            for line in self._proc.stderr:
                text = line.rstrip("\n")
                self._stderr.append(text)
                found = WARNING_LINE.match(text.strip())
                if found and found.group(1) not in self.warnings:
                    self.warnings.append(found.group(1))
        except (OSError, ValueError):
            pass

    def _read_stdout(self) -> None:
        assert self._proc.stdout is not None
        try:
            for line in self._proc.stdout:
                if line.strip():
                    self._events.put(parse_progress_line(line))
        except (OSError, ValueError) as exc:  # pipe closed under us (cancel) or unreadable output
            self._stderr.append(f"reading progress failed: {exc}")
        finally:
            # whatever happened, the main thread must learn that the process is over
            returncode = self._proc.wait()
            self._err_thread.join(timeout=5.0)
            self._events.put({"stage": "_exit", "returncode": returncode})

    # -- main thread --------------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        return self.state == "running"

    @property
    def pid(self) -> int:
        return self._proc.pid

    def stderr_text(self) -> str:
        return "\n".join(self._stderr)

    def poll_once(self) -> bool:
        """Drain pending events, update progress, finish the job when the process has exited.

        Main thread only. Returns True while the job is still running.
        """
        if self.state != "running":
            return False
        if self.finishing is not None:
            self._step_finishing()
        while self.state == "running" and self.finishing is None:
            try:
                event = self._events.get_nowait()
            except queue.Empty:
                break
            self._handle(event)
        self.publish()
        if self.state != "running" and not self._ended:
            self._ended = True
            self.on_end()
        return self.state == "running"

    def wait(self, timeout: float | None = None, interval: float = 0.05,
             on_poll: Callable[["Job"], None] | None = None) -> str:
        """Drive `poll_once` until the job ends (batch mode and tests); cancels on timeout."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.poll_once():
            if on_poll is not None:
                on_poll(self)
            if deadline is not None and time.monotonic() > deadline:
                self.cancel()
                self.error = f"timed out after {timeout:.0f} s"
                break
            time.sleep(interval)
        return self.state

    def kill(self) -> None:
        """Stop the process tree and remove the temporary files without touching Blender (interpreter exit)."""
        if self.state == "running":
            _terminate_tree(self._proc)
            self.state = "cancelled"
            self._cleanup()

    def cancel(self) -> None:
        """Kill the process (and its children) and drop the temporary files; nothing is built."""
        if self._stop():
            self.state = "cancelled"
            self.status = "Cancelled"
            self.publish()

    def _stop(self) -> bool:
        """End a running process, the results it was adding (removed again) and its files; False when the job had
        already ended."""
        if self.state != "running":
            return False
        if self.finishing is not None:
            self.finishing.cancel()
            self.finishing = None
        _terminate_tree(self._proc)
        self._out_thread.join(timeout=5.0)
        self._cleanup()
        return True

    def _handle(self, event: dict[str, Any]) -> None:
        stage = str(event.get("stage", ""))
        if stage == "_exit":
            self._finish(int(event["returncode"]))
            return
        if stage == "log":
            return
        mismatch = protocol_error(event, self.cmd[0])
        if mismatch:
            if self._stop():
                self._fail(mismatch)
        elif stage == "done":
            self._done_event = event
            self.status = "Building results"
        elif stage == "error":
            self._reported_error = str(event.get("message") or "hgca_core reported an error")
        else:
            self.on_progress(stage, event)

    def _finish(self, returncode: int) -> None:
        self.returncode = returncode
        try:
            if returncode == 0 and self._done_event is not None:
                self.outputs = self._output_paths(self._done_event)
                self.finishing = self.on_success(self.outputs)
                if self.finishing is None:
                    self._succeed()
                else:
                    self.status = self.finishing.status
            else:
                if returncode == 0:
                    message = "hgca_core finished without reporting its outputs"
                elif returncode < 0 and not self._reported_error:
                    message = killed_message(-returncode)
                else:
                    message = self._reported_error or error_message(self.stderr_text(), returncode, self.cmd[0])
                self._fail(message)
        except Exception as exc:  # building results failed: on_success rolled back, report why
            self._fail(f"could not load the results: {exc}")
        if self.finishing is None:
            self._cleanup()

    def _succeed(self) -> None:
        self.state, self.progress, self.status = "done", 1.0, self.success_status()

    def _step_finishing(self) -> None:
        """One time-bounded slice of the results going in (`result_insert.Insertion`); the job ends with them."""
        finishing = self.finishing
        if finishing.step():
            self.status = finishing.status
            return
        self.finishing = None
        try:
            if finishing.error:
                raise RuntimeError(finishing.error)
            self.on_inserted(finishing)
            self._succeed()
        except Exception as exc:  # noqa: BLE001  (the insertion removed what it made)
            self._fail(f"could not load the results: {exc}")
        self._cleanup()

    def _fail(self, message: str) -> None:
        self.state = "error"
        self.error = message
        self.status = f"Error: {message}"

    def _output_paths(self, done: dict[str, Any]) -> list[Path]:
        listed = done.get("outputs")
        paths = [Path(p) if Path(p).is_absolute() else self.workdir / p for p in listed] \
            if isinstance(listed, list) else []
        missing = [str(p) for p in paths if not p.is_file()]
        if not paths or missing:
            raise CoreError(f"output files missing: {', '.join(missing) or 'none reported'}")
        return paths

    def _cleanup(self) -> None:
        shutil.rmtree(self.workdir, ignore_errors=True)

    # -- hooks ---------------------------------------------------------------------------------------
    def on_progress(self, stage: str, event: dict[str, Any]) -> None:
        """A progress record (any stage but done/error); update `progress` and `status` (main thread)."""

    def on_success(self, outputs: list[Path]) -> Any:
        """Consume the outputs (main thread). Must leave Blender untouched if it raises. May return an insertion
        (`step()`, `cancel()`, `status`, `error`): the job then runs on until it is done, then `on_inserted`."""

    def on_inserted(self, insertion: Any) -> None:
        """The results `on_success` began are in the scene (main thread)."""

    def success_status(self) -> str:
        return "Done"

    def on_end(self) -> None:
        """Once, after the job reached a terminal state in `poll_once` (main thread): say what it has to say."""

    def publish(self) -> None:
        """Show progress somewhere (main thread)."""
