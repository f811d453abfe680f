"""Load: 20 jobs submitted concurrently by 4 clients (4 owners, 5 jobs each, the 5 of a client
also sent at once) while 2 more clients poll job status and job lists steadily. Every job
finishes, none is lost, duplicated or run twice, nobody sees another owner's jobs, no request
gets a 5xx, the two job slots are never exceeded; the figures (throughput, status latency
percentiles) are printed and written to ``load-figures.json`` beside the server log.

Four owners rather than two owners with two clients each: each owner's list must then hold
exactly the 5 jobs its client submitted, which checks both that concurrent submissions of one
owner (the 5 of a client race each other) are all kept and that no job leaks into another
owner's list."""

from __future__ import annotations

import json
import statistics
import threading
import time
import urllib.error
import urllib.request
from concurrent.futures import ThreadPoolExecutor

from .conftest import FAST, Service, upload_inputs

CLIENTS, JOBS_PER_CLIENT, POLLERS, SLOTS = 4, 5, 2, 2
# seconds for all 20 jobs to finish: generous, the CPUs are shared (and without the service's atlas
# cache every job builds its own contact atlas, ~20 s of CPU each)
TIMEOUT = 20 * 60
POLL_PAUSE = 0.1  # between two requests of one poller
STATE_ORDER = {"queued": 0, "running": 1, "succeeded": 2, "failed": 2, "cancelled": 2}


def _call(base: str, token: str, method: str, path: str, doc=None) -> tuple[int, object]:
    """One request; (HTTP status, JSON body). Raw urllib rather than the client, whose calls
    return only the body: the status code itself is what is checked here."""
    body = None if doc is None else json.dumps(doc).encode()
    req = urllib.request.Request(base + path, data=body, method=method,
                                 headers={"Authorization": f"Bearer {token}", "Accept": "application/json",
                                          **({"Content-Type": "application/json"} if body else {})})
    try:
        with urllib.request.urlopen(req, timeout=120) as resp:
            return resp.status, json.loads(resp.read())
    except urllib.error.HTTPError as err:
        text = err.read().decode("utf-8", "replace")
        try:
            return err.code, json.loads(text)
        except ValueError:
            return err.code, text


def _percentile(values: list[float], q: float) -> float:
    """The ``q``-th percentile (0-100) by linear interpolation between the closest ranks."""
    s = sorted(values)
    if len(s) == 1:
        return s[0]
    pos = (len(s) - 1) * q / 100
    lo = int(pos)
    hi = min(lo + 1, len(s) - 1)
    return s[lo] + (s[hi] - s[lo]) * (pos - lo)


class Poller(threading.Thread):
    """Asks GET /v1/jobs/{id} (round robin over the submitted jobs) and GET /v1/jobs (round
    robin over the owners) in turn until stopped; records each request's latency and status."""

    def __init__(self, base, tokens, submitted, lock, stop):
        super().__init__(daemon=True)
        self.base, self.tokens, self.submitted, self.lock, self.stop = base, tokens, submitted, lock, stop
        self.samples = []  # (kind, seconds, status)
        self.states = {}  # job id -> states seen, in order
        self.errors = []  # transport-level failures (no HTTP answer)

    def _timed(self, kind, owner, path):
        start = time.perf_counter()
        try:
            status, doc = _call(self.base, self.tokens[owner], "GET", path)
        except Exception as err:  # noqa: BLE001 - a refused or timed-out request is a finding, not a crash
            self.errors.append(f"{kind}: {type(err).__name__}: {err}")
            return None
        self.samples.append((kind, time.perf_counter() - start, status))
        return doc if status == 200 else None

    def _see(self, job):
        seen = self.states.setdefault(job["id"], [])
        if not seen or seen[-1] != job["state"]:
            seen.append(job["state"])

    def run(self):
        owners = sorted(self.tokens)
        i = 0
        while not self.stop.is_set():
            with self.lock:
                jobs = list(self.submitted)
            if jobs:
                owner, job_id = jobs[i % len(jobs)]
                job = self._timed("status", owner, f"/v1/jobs/{job_id}")
                if job is not None:
                    self._see(job)
            listed = self._timed("list", owners[i % len(owners)], "/v1/jobs")
            for job in (listed or {}).get("jobs", []):
                self._see(job)
            i += 1
            self.stop.wait(POLL_PAUSE)


def test_twenty_jobs_from_four_clients_with_steady_polling(tmp_path_factory, inputs):
    root = tmp_path_factory.mktemp("load")
    svc = Service(root / "data", "--job-slots", str(SLOTS)).start()
    stop = threading.Event()
    pollers = []
    try:
        owners = [f"load-owner-{k}" for k in range(CLIENTS)]
        clients = {o: svc.client(o) for o in owners}
        tokens = {o: c.token for o, c in clients.items()}
        with ThreadPoolExecutor(CLIENTS) as pool:  # every owner uploads the same inputs at once
            t0 = time.monotonic()
            ids = dict(zip(owners, pool.map(lambda o: upload_inputs(clients[o], inputs), owners)))
            upload_seconds = time.monotonic() - t0
        assert len({json.dumps(v, sort_keys=True) for v in ids.values()}) == 1  # content-addressed: same ids

        submitted, lock = [], threading.Lock()
        for _ in range(POLLERS):
            pollers.append(Poller(svc.url, tokens, submitted, lock, stop))
            pollers[-1].start()

        barrier = threading.Barrier(CLIENTS * JOBS_PER_CLIENT)

        def submit(owner, k):
            maxeval = 15 + owners.index(owner) * JOBS_PER_CLIENT + k  # 15..34: 20 distinct requests
            doc = {**ids[owner], "preset": "default", "overrides": FAST | {"solver.maxeval": maxeval},
                   "evaluate": False}  # what RetargetClient.submit sends
            barrier.wait(timeout=60)  # all 20 POSTs leave together
            status, job = _call(svc.url, tokens[owner], "POST", "/v1/jobs", doc)
            if status == 201:
                with lock:
                    submitted.append((owner, job["id"]))
            return owner, maxeval, status, job

        t_submit = time.monotonic()
        with ThreadPoolExecutor(CLIENTS * JOBS_PER_CLIENT) as pool:
            results = list(pool.map(lambda a: submit(*a), [(o, k) for o in owners for k in range(JOBS_PER_CLIENT)]))
        submit_seconds = time.monotonic() - t_submit
        bad = [r for r in results if r[2] != 201]  # 201: a new job (200 would be an earlier one)
        assert not bad, bad
        job_ids = [r[3]["id"] for r in results]
        assert len(set(job_ids)) == CLIENTS * JOBS_PER_CLIENT, "two submissions got the same job"
        assert all(r[3]["state"] in ("queued", "running") for r in results)
        assert sorted(r[3]["request"]["overrides"]["solver.maxeval"] for r in results) == list(range(15, 35))
        mine = {o: {r[3]["id"] for r in results if r[0] == o} for o in owners}

        deadline = time.monotonic() + TIMEOUT
        final = {}
        for owner, maxeval, _, job in results:
            remaining = deadline - time.monotonic()
            assert remaining > 0, f"not all jobs finished within {TIMEOUT} s: {len(final)} did"
            final[job["id"]] = clients[owner].wait(job["id"], timeout=remaining, poll=1.0)
        stop.set()
        for p in pollers:
            p.join(timeout=180)
            assert not p.is_alive(), "a poller hangs"

        # every job ran once to success
        failed = {j: (f["state"], f["error"]) for j, f in final.items() if f["state"] != "succeeded"}
        assert not failed, failed
        assert all(f["attempts"] == 1 for f in final.values()), [f["attempts"] for f in final.values()]
        assert all(f["frames_done"] == f["frames_total"] == 46 for f in final.values())
        assert all("animation.usda" in f["artifacts"] for f in final.values())
        # each owner's list: exactly its 5 jobs, each once, nothing of anyone else
        for owner in owners:
            listed = [j["id"] for j in clients[owner].jobs()]
            assert len(listed) == JOBS_PER_CLIENT and set(listed) == mine[owner], (owner, listed, mine[owner])
            for other in owners:
                if other != owner:
                    assert not set(listed) & mine[other]
        # nothing else in the store: 20 succeeded jobs in all
        from server.storage import Store  # /v1/ready shows no counts (issue 16): read the store

        counts = Store(svc.data_dir).state_counts()
        assert counts == {"queued": 0, "running": 0, "succeeded": 20, "failed": 0, "cancelled": 0}, counts
        # the job slots were respected: never more than 2 jobs between claim and finish at once
        events = sorted([(f["started"], 1) for f in final.values()] + [(f["finished"], -1) for f in final.values()],
                        key=lambda e: (e[0], e[1]))
        running = peak = 0
        for _, delta in events:
            running += delta
            peak = max(peak, running)
        assert peak <= SLOTS, f"{peak} jobs ran at once with {SLOTS} slots"
        # what the pollers saw: answers only (no 5xx, no transport errors), states only move forward
        samples = [s for p in pollers for s in p.samples]
        errors = [e for p in pollers for e in p.errors]
        assert not errors, errors[:5]
        server_errors = [s for s in samples if s[2] >= 500]
        assert not server_errors, server_errors[:5]
        assert all(s[2] == 200 for s in samples), sorted({s[2] for s in samples})
        for p in pollers:
            for job_id, seen in p.states.items():
                assert job_id in final
                ranks = [STATE_ORDER[s] for s in seen]
                assert ranks == sorted(ranks), (job_id, seen)

        status_ms = [1000 * s[1] for s in samples if s[0] == "status"]
        list_ms = [1000 * s[1] for s in samples if s[0] == "list"]
        assert len(status_ms) >= 20 and len(list_ms) >= 20, "the pollers hardly polled"
        first_created = min(f["created"] for f in final.values())
        last_finished = max(f["finished"] for f in final.values())
        wall = last_finished - first_created
        job_seconds = [f["finished"] - f["started"] for f in final.values()]
        figures = {
            "jobs": len(final),
            "clients": CLIENTS,
            "pollers": POLLERS,
            "job_slots": SLOTS,
            # atlases in the service's cache (DATA/cache/atlas) after the run, where the jobs found them
            "atlas_cache_files": len(list((svc.data_dir / "cache" / "atlas").glob("*.npz"))),
            "upload_seconds": round(upload_seconds, 2),
            "submit_seconds": round(submit_seconds, 3),
            "wall_seconds": round(wall, 2),
            "throughput_jobs_per_min": round(60 * len(final) / wall, 3),
            "job_seconds_median": round(statistics.median(job_seconds), 2),
            "job_seconds_max": round(max(job_seconds), 2),
            "polls": len(samples),
            "status_polls": len(status_ms),
            "list_polls": len(list_ms),
            "status_latency_ms_p50": round(_percentile(status_ms, 50), 2),
            "status_latency_ms_p99": round(_percentile(status_ms, 99), 2),
            "status_latency_ms_max": round(max(status_ms), 2),
            "list_latency_ms_p50": round(_percentile(list_ms, 50), 2),
            "list_latency_ms_p99": round(_percentile(list_ms, 99), 2),
            "poll_statuses": sorted({s[2] for s in samples}),
        }
        out = svc.log.parent / "load-figures.json"
        out.write_text(json.dumps(figures, indent=2) + "\n")
        print(f"\nload figures ({out}):\n{json.dumps(figures, indent=2)}")
    finally:
        stop.set()
        svc.stop()
