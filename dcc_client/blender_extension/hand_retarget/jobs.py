"""The service connection and the job poller.

Blender must stay responsive while a job runs, so nothing waits: :func:`poll_job` is a
``bpy.app.timers`` callback that starts each HTTP request in a thread and, on its next call,
copies the answer into the scene's properties (panel, status bar). Its state lives in the
module (``STATE``), not in the function, so tests can drive it in a loop: timers never fire in
the ``bpy`` module (dcc_client/BLENDER_NOTES.md, section 8).
"""

from __future__ import annotations

import threading
import time
import urllib.parse

import bpy

from . import client as service

POLL_INTERVAL = 0.5     # seconds between status requests
BUSY_INTERVAL = 0.1     # seconds between checks while a request is in flight
MAX_FAILURES = 20       # consecutive failed requests before the poller gives up
LOOPBACK = ("127.0.0.1", "localhost", "::1")

STATE = {"job_id": None, "scene": None, "client": None, "thread": None, "reply": None, "error": None,
         "failures": 0, "progress_on": False, "on_done": None}


class ConnectionSettingsError(RuntimeError):
    """The server URL / token preferences are missing or not allowed."""


def preferences(context=None):
    context = context or bpy.context
    addon = context.preferences.addons.get(__package__)
    if addon is None:
        raise ConnectionSettingsError(f"the add-on {__package__} is not enabled")
    return addon.preferences


def make_client(context=None, timeout: float = 120.0) -> service.RetargetClient:
    """A client for the URL and token in the add-on preferences. Non-loopback servers need
    Blender's "Allow Online Access" (Preferences > System), as Blender asks of add-ons."""
    prefs = preferences(context)
    url = (prefs.server_url or "").strip()
    if not url:
        raise ConnectionSettingsError("set the server URL in the add-on preferences")
    host = urllib.parse.urlparse(url).hostname or ""
    if host not in LOOPBACK and not bpy.app.online_access:
        raise ConnectionSettingsError("online access is off (Preferences > System > Network); "
                                      f"{host} is not this computer")
    if not prefs.token:
        raise ConnectionSettingsError("set the access token in the add-on preferences")
    return service.RetargetClient(url, prefs.token, timeout=timeout)


# ---- polling --------------------------------------------------------------------------------------
def _fetch(client, job_id, state):
    try:
        state["reply"], state["error"] = client.job(job_id), None
    except Exception as exc:  # network trouble is reported, never raised into Blender
        state["reply"], state["error"] = None, exc


def _redraw():
    wm = bpy.context.window_manager
    for window in getattr(wm, "windows", []):
        for area in window.screen.areas:
            if area.type in ('VIEW_3D', 'STATUSBAR'):
                area.tag_redraw()


def _progress(on: bool, value: float = 0.0):
    wm = bpy.context.window_manager
    if wm is None:
        return
    if on:
        if not STATE["progress_on"]:
            wm.progress_begin(0.0, 1.0)
            STATE["progress_on"] = True
        wm.progress_update(min(max(value, 0.0), 1.0))
    elif STATE["progress_on"]:
        wm.progress_end()
        STATE["progress_on"] = False


def apply_job(settings, job: dict):
    """Copy a job's status into the scene settings the panel and the status bar show."""
    settings.job_id = job["id"]
    settings.job_state = job["state"]
    settings.job_stage = job.get("stage") or ""
    settings.job_progress = float(job.get("progress") or 0.0)
    done, total = job.get("frames_done") or 0, job.get("frames_total") or 0
    frames = f", frame {done}/{total}" if total else ""
    settings.job_message = (job.get("error") or "") if job["state"] == "failed" else \
        f"{job['state']}: {settings.job_stage} {100 * settings.job_progress:.0f}%{frames}"


def poll_job():
    """The timer callback: returns the seconds until the next call, or None when the job has
    reached a final state (or the poller gave up)."""
    st = STATE
    if st["job_id"] is None:
        return None
    scene = bpy.data.scenes.get(st["scene"] or "")
    thread = st["thread"]
    if thread is not None and thread.is_alive():
        return BUSY_INTERVAL
    if thread is not None:
        st["thread"] = None
        settings = scene.hand_retarget if scene is not None else None
        if st["error"] is not None:
            st["failures"] += 1
            if settings is not None:
                settings.job_message = f"cannot reach the service ({st['failures']}): {st['error']}"
            if st["failures"] >= MAX_FAILURES:
                stop_polling()
                return None
            return POLL_INTERVAL
        st["failures"] = 0
        job = st["reply"]
        if settings is not None:
            apply_job(settings, job)
        _progress(job["state"] not in service.FINAL_STATES, float(job.get("progress") or 0.0))
        _redraw()
        if job["state"] in service.FINAL_STATES:
            on_done = st["on_done"]
            stop_polling()
            if on_done is not None and scene is not None:
                on_done(scene, job)
            return None
        return POLL_INTERVAL
    st["thread"] = threading.Thread(target=_fetch, args=(st["client"], st["job_id"], st), daemon=True)
    st["thread"].start()
    return BUSY_INTERVAL


def start_polling(client, job_id: str, scene, on_done=None):
    """Follow ``job_id`` with the timer; ``on_done(scene, job)`` once it is final."""
    stop_polling()
    STATE.update(job_id=job_id, scene=scene.name, client=client, thread=None, reply=None, error=None,
                 failures=0, on_done=on_done)
    if not bpy.app.timers.is_registered(poll_job):
        bpy.app.timers.register(poll_job, first_interval=0.0)


def stop_polling():
    if bpy.app.timers.is_registered(poll_job):
        bpy.app.timers.unregister(poll_job)
    _progress(False)
    STATE.update(job_id=None, client=None, thread=None, reply=None, error=None, on_done=None)


def is_polling() -> bool:
    return STATE["job_id"] is not None


def drive(timeout: float = 600.0):
    """Run the poller to the end without Blender's event loop (tests, scripts): call the timer
    function as Blender would. Returns when it is done; TimeoutError after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while is_polling():
        nxt = poll_job()
        if nxt is None:
            break
        if time.monotonic() > deadline:
            raise TimeoutError(f"job {STATE['job_id']} not final after {timeout:g} s")
        time.sleep(nxt)
    if bpy.app.timers.is_registered(poll_job):
        bpy.app.timers.unregister(poll_job)
