"""The node under load and faults for a stated time (issue 54); scripts/soak runs it.

For each path (single-frequency: depth, IR, camera_info; multi-frequency: the
same and one phasor image per frequency), it starts the node, a camera driver
(soak_peers.py player: a 640x480 recording in a loop at 30 Hz, stamped with the
wall clock), a consumer (soak_peers.py monitor) and a reliable reader that is
stopped and let go on; latches the empty scene, plays the object, warms up,
then injects faults drawn from the seed on a schedule:

  malformed       samples that do not decode and images shorter than their size
  burst           frames at 3x the rate
  player_crash    the driver killed (SIGKILL) and started again
  reader_stall    a reliable reader stopped (SIGSTOP), then let go on (SIGCONT)
  latch_in_view   ~/latch_background called with the object in view; then the
                  empty scene latched again (the fault's end)
  parameters      threshold_mm set at run time, then set back
  camera_moved    every valid depth 500 mm farther (the camera stepped back), then back

Every second it samples the node's resident memory and CPU time (/proc), the
outputs that arrived and their latency (from the input's stamp, the wall clock
when the driver published it, to the corrected depth's arrival at the
consumer). Then it checks, on what the node output:

  rss        resident memory at the end within --rss-tolerance (5 %) of its value
             after the warm-up (each the median over --rss-span, 30 s: five of the
             DDS writers' 6 s clean-up periods, at most a quarter of the measured time)
  latency    p99 at most --p99-ratio (2x) the median in every window
  rate       every window's output rate within --rate-tolerance (5 %) of their mean
  counted    every fault counted in /diagnostics and in the node's --stats-json
  resumed    a corrected frame (non-empty mask) within --resume-s (1 s) of each fault's end
  no_crash   the node alive to the end, exiting 0 on SIGINT, no panic in its log

The windows: the time after the warm-up cut into 6 (the one-hour run's six
10-minute windows; shorter runs scale them, at least 30 s each); each fault's
period and 1 s after it are left out of the latency and rate windows. Exits 1
naming each condition that failed and by how much.
"""

import argparse
import json
import math
import os
import random
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
PEERS = REPO / "scripts" / "soak_peers.py"
FAULTS = ["malformed", "burst", "player_crash", "reader_stall", "latch_in_view", "parameters", "camera_moved"]
CLK_TCK = os.sysconf("SC_CLK_TCK")
PAGE_KB = os.sysconf("SC_PAGE_SIZE") // 1024


def duration(text):
    m = re.fullmatch(r"(\d+(?:\.\d+)?)([smh]?)", text)
    if not m:
        raise argparse.ArgumentTypeError(f"{text!r}: a duration is a number with s, m or h (90s, 15m, 1h)")
    return float(m.group(1)) * {"": 1, "s": 1, "m": 60, "h": 3600}[m.group(2)]


def percentile(xs, q):
    if not xs:
        return float("nan")
    xs = sorted(xs)
    i = (len(xs) - 1) * q / 100.0
    lo, hi = math.floor(i), math.ceil(i)
    return xs[lo] + (xs[hi] - xs[lo]) * (i - lo)


class Progress:
    def __init__(self, quiet):
        self.quiet = quiet or not sys.stderr.isatty()
        self.last = 0.0

    def line(self, text, force=False):
        if self.quiet or (not force and time.monotonic() - self.last < 2.0):
            return
        self.last = time.monotonic()
        sys.stderr.write(f"\r\x1b[K{text}")
        sys.stderr.flush()

    def done(self):
        if not self.quiet:
            sys.stderr.write("\n")


class Peer:
    """A soak_peers.py process: commands on its stdin, its lines collected by a thread."""

    def __init__(self, role, args, env, log):
        self.role = role
        self.p = subprocess.Popen(
            [sys.executable, str(PEERS), role, *args],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=open(log, "ab"),
            text=True, bufsize=1, env=env,
        )
        self.lines = []
        self.lock = threading.Lock()
        self.on_line = None
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self):
        for line in self.p.stdout:
            if self.on_line is not None:
                self.on_line(line.split(" ", 2))
            else:
                with self.lock:
                    self.lines.append(line.split())

    def send(self, cmd):
        try:
            self.p.stdin.write(cmd + "\n")
            self.p.stdin.flush()
        except (BrokenPipeError, OSError):
            pass

    def take(self):
        with self.lock:
            out, self.lines = self.lines, []
        return out

    def stop(self, timeout=10):
        if self.p.poll() is None:
            self.send("quit")
            try:
                self.p.wait(timeout)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait()


class Run:
    """One path's soak."""

    def __init__(self, a, path, bag, out, progress):
        self.a, self.path, self.bag, self.out, self.progress = a, path, bag, out, progress
        self.rng = random.Random(f"{a.seed}:{path}")
        self.env = dict(os.environ, ROS_LOCALHOST_ONLY="1")
        # The peers' Fast DDS with 4 MiB socket buffers (docs/performance.md), where the
        # kernel allows them.
        rmem_max = int(Path("/proc/sys/net/core/rmem_max").read_text().strip() or 0)
        if rmem_max >= 4 << 20:
            self.env.setdefault("FASTDDS_DEFAULT_PROFILES_FILE", str(REPO / "config" / "fastdds_large_data.xml"))
        self.corrected = {}  # stamp -> arrival (ns)
        self.masks = {}  # stamp -> corrected (non-empty mask)
        self.diag = []  # (t_ns, values)
        self.replies = []
        self.samples = []
        self.faults = []
        self.player_sent = 0
        self.player_first = None
        self.lock = threading.Lock()
        # --skip KIND or PATH:KIND: faults not injected on this path (the report lists them).
        self.skipped = sorted({x.split(":")[-1] for x in a.skip if ":" not in x or x.split(":")[0] == path})

    # -- the processes ------------------------------------------------------------
    def start(self):
        a = self.a
        self.stats_json = self.out / f"{self.path}.stats.json"
        self.node_log = self.out / f"{self.path}.node.log"
        args = [
            a.node, "node", "--stats-json", str(self.stats_json), "--ros-args", "-r", "__ns:=/tof",
            "-p", "physics:=paper", "-p", f"background_frames:={a.background_frames}",
            # A latch at 640x480 on the multi-frequency path, which loses inputs, can take
            # longer than the default 10 s to gather its frames.
            "-p", "latch_timeout_s:=30.0",
        ]
        if a.xi != "estimate":
            args += ["-p", f"xi:={a.xi}"]
        if self.path == "multi_frequency":
            args += ["-p", "modulation_frequencies_hz:=[20000000.0, 50000000.0, 100000000.0]"]
        self.node = subprocess.Popen(args, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                     stderr=open(self.node_log, "wb"), env=self.env)
        self.cpu0 = None
        fqn = "/tof/translucent_tof"
        self.monitor = Peer("monitor", [fqn], self.env, self.out / f"{self.path}.monitor.log")
        self.monitor.on_line = self._monitor_line
        self.reader = Peer("reader", [fqn], self.env, self.out / f"{self.path}.reader.log")
        self.reader.on_line = lambda w: None
        self.player = self._start_player("background")
        self._wait(lambda: self.player_first is not None, 90, "the player's first frame")

    def _start_player(self, mode):
        self.player_first = None
        p = Peer("player", [str(self.bag), "/tof", "--mode", mode, "--rate", str(self.a.rate)], self.env,
                 self.out / f"{self.path}.player.log")
        p.on_line = self._player_line
        return p

    def _player_line(self, w):
        if w[0] == "first":
            self.player_first = int(w[1])
            self.malformed_sent = int(w[2])
        elif w[0] == "sent":
            self.player_sent_now = int(w[1])
        elif w[0] == "malformed_sent":
            self.malformed_sent = int(w[1])

    def _monitor_line(self, w):
        with self.lock:
            if w[0] == "c":
                self.corrected[int(w[1])] = int(w[2])
            elif w[0] == "m":
                self.masks[int(w[1])] = w[2].strip() == "1"
            elif w[0] == "d":
                d = json.loads(w[1] + (" " + w[2] if len(w) > 2 else ""))
                self.diag.append((d["t"], d["values"]))
            elif w[0] == "r":
                self.replies.append(" ".join(w[1:]).strip())
            elif w[0] == "ready":
                self.monitor_ready = True

    def _wait(self, cond, timeout, what):
        end = time.monotonic() + timeout
        while not cond():
            if time.monotonic() > end:
                raise SystemExit(f"soak ({self.path}): no {what} in {timeout:.0f} s")
            self._tick()
            time.sleep(0.05)

    def _reply(self, kind, timeout=30):
        end = time.monotonic() + timeout
        while True:
            with self.lock:
                for r in self.replies:
                    if r.startswith(kind):
                        self.replies.remove(r)
                        ok, _, msg = r[len(kind) + 1:].partition(" ")
                        return ok == "1", msg
            if time.monotonic() > end:
                return False, f"no reply to {kind} in {timeout} s"
            self._tick()
            time.sleep(0.05)

    # -- sampling ---------------------------------------------------------------
    def _tick(self):
        """Samples the node once a second (called while waiting)."""
        now = time.time()
        if self.samples and now - self.samples[-1]["t"] < 1.0:
            return
        try:
            stat = Path(f"/proc/{self.node.pid}/stat").read_text().rsplit(")", 1)[1].split()
            statm = Path(f"/proc/{self.node.pid}/statm").read_text().split()
        except OSError:
            return
        cpu = (int(stat[11]) + int(stat[12])) / CLK_TCK
        rss_kb = int(statm[1]) * PAGE_KB
        prev = self.samples[-1] if self.samples else None
        cpu_pct = 100.0 * (cpu - prev["cpu_s"]) / (now - prev["t"]) if prev else 0.0
        self.samples.append({"t": now, "rss_kb": rss_kb, "cpu_s": cpu, "cpu_pct": round(cpu_pct, 1)})
        if self.t_measure is not None:
            el = now - self.t_start
            with self.lock:
                n = len(self.corrected)
            self.progress.line(
                f"{self.path}: {el:.0f}/{self.t_end - self.t_start:.0f} s, RSS {rss_kb / 1024:.0f} MB, "
                f"CPU {cpu_pct:.0f} %, {n} outputs, {len(self.faults)} faults"
            )

    def wait(self, seconds):
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self._tick()
            time.sleep(min(0.1, max(0.0, end - time.monotonic())))

    def diag_now(self):
        with self.lock:
            return dict(self.diag[-1][1]) if self.diag else {}

    def diag_after(self, t_ns, timeout=5.0):
        """The first /diagnostics published after wall time t_ns (they come every second)."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            with self.lock:
                for t, v in self.diag:
                    if t > t_ns:
                        return dict(v)
            self._tick()
            time.sleep(0.05)
        return self.diag_now()

    # -- the run ----------------------------------------------------------------
    def run(self):
        a = self.a
        self.t_measure = None
        self.t_start = time.time()
        self.start()
        self._wait(lambda: getattr(self, "monitor_ready", False), 60, "monitor")
        # Latch the empty scene, then the object comes into view.
        self.monitor.send("latch")
        ok, msg = self._reply("latch", 60)
        if not ok:
            raise SystemExit(f"soak ({self.path}): the first latch failed: {msg}")
        self.player.send("mode objects")
        self.t_start = time.time()
        self.t_end = self.t_start + a.duration
        self.t_measure = self.t_start + a.warmup
        self.wait(a.warmup)
        plan = self.plan()
        for kind, gap, params in plan:
            self.wait(gap)
            getattr(self, f"fault_{kind}")(params)
        # A schedule that ran over (a slow restart, a slow latch) ends 5 s after its last fault.
        self.wait(max(5.0, self.t_end - time.time()))
        self.t_end = max(self.t_end, time.time())
        return self.finish(plan)

    def plan(self):
        """The faults in a seeded order, each kind once per round, as many rounds as fit
        with at least --gap s between faults; the gaps drawn between --gap and twice it,
        shrunk for a short run so that one round fits."""
        a = self.a
        est = {"malformed": 1, "burst": 3, "player_crash": 6, "reader_stall": 5, "latch_in_view": 4,
               "parameters": 4, "camera_moved": 3}
        room = a.duration - a.warmup - 10
        per_round = sum(est.values()) + len(FAULTS) * 1.5 * a.gap
        rounds = max(1, int(room // per_round))
        gap = a.gap if room >= per_round else max(2.0, (room - sum(est.values())) / len(FAULTS) / 1.5)
        plan = []
        for _ in range(rounds):
            kinds = FAULTS[:]
            self.rng.shuffle(kinds)
            for k in kinds:
                if k in self.skipped:
                    continue
                params = {
                    "malformed": {"n": self.rng.randint(5, 20)},
                    "burst": {"s": self.rng.uniform(2, 4)},
                    "player_crash": {"down_s": self.rng.uniform(1, 3)},
                    "reader_stall": {"s": self.rng.uniform(3, 6)},
                    "latch_in_view": {},
                    "parameters": {"threshold_mm": self.rng.choice([25.0, 40.0, 50.0]), "s": self.rng.uniform(2, 4)},
                    "camera_moved": {"s": self.rng.uniform(2, 4)},
                }[k]
                plan.append((k, self.rng.uniform(gap, 2 * gap), params))
        return plan

    def _fault(self, kind, params, start_ns, end_ns, counted, note=""):
        self.faults.append({"kind": kind, "params": params, "start_ns": start_ns, "end_ns": end_ns,
                            "counted": counted, "note": note})

    def fault_malformed(self, p):
        before = self.diag_now()
        self.player_first = None
        t0 = time.time_ns()
        self.player.send(f"malformed {p['n']}")
        # Its end: the driver's first frame after the samples (sending them holds it up).
        self._wait(lambda: self.player_first is not None, 30, "frame after the malformed samples")
        t1 = self.player_first
        after = self.diag_after(t1 + 1_200_000_000)
        keys = ["dropped_malformed", "dropped_oversized", "dropped_bad_image", "dropped_size_mismatch"]
        n = sum(cnt(after, k) - cnt(before, k) for k in keys)
        self._fault("malformed", p, t0, t1, {"diagnostics": {"sent": self.malformed_sent, "dropped": n,
                                                            "ok": n >= self.malformed_sent}},
                    note="dropped_malformed + dropped_oversized + dropped_bad_image + dropped_size_mismatch")
        self.malformed_total = getattr(self, "malformed_total", 0) + self.malformed_sent

    def fault_burst(self, p):
        before = self.diag_now()
        sent0 = getattr(self, "player_sent_now", 0)
        t0 = time.time_ns()
        self.player.send("rate_factor 3")
        self.wait(p["s"])
        self.player.send("rate_factor 1")
        t1 = time.time_ns()
        self.wait(1.5)
        after = self.diag_after(time.time_ns())
        sent = getattr(self, "player_sent_now", 0) - sent0
        got = cnt(after, "depth_received") - cnt(before, "depth_received")
        qf = cnt(after, "dropped_queue_full") - cnt(before, "dropped_queue_full")
        ok = got >= 0.8 * sent and qf > 0
        self._fault("burst", p, t0, t1, {"diagnostics": {"frames_sent": sent, "depth_received": got,
                                                        "dropped_queue_full": qf, "ok": ok}},
                    note="depth_received grows by the frames sent (80 % or more) and dropped_queue_full grows")

    def fault_player_crash(self, p):
        before = self.diag_now()
        t0 = time.time_ns()
        self.player.p.kill()
        self.player.p.wait()
        self.wait(p["down_s"])
        self.player = self._start_player("objects")
        self._wait(lambda: self.player_first is not None, 90, "restarted player's first frame")
        t1 = self.player_first
        after = self.diag_after(t1 + 500_000_000)
        n = cnt(after, "input_gaps") - cnt(before, "input_gaps")
        self._fault("player_crash", p, t0, t1, {"diagnostics": {"input_gaps": n, "ok": n >= 1}},
                    note="its end: the restarted driver's first frame")
        self.crashes = getattr(self, "crashes", 0) + 1

    def fault_reader_stall(self, p):
        before = self.diag_now()
        t0 = time.time_ns()
        os.kill(self.reader.p.pid, signal.SIGSTOP)
        self.wait(p["s"])
        os.kill(self.reader.p.pid, signal.SIGCONT)
        t1 = time.time_ns()
        after = self.diag_after(t1 + 500_000_000)
        n = cnt(after, "publish_failures") - cnt(before, "publish_failures")
        self._fault("reader_stall", p, t0, t1, {"diagnostics": {"publish_failures": n, "ok": n >= 1}})
        self.stalls = getattr(self, "stalls", 0) + 1

    def fault_latch_in_view(self, p):
        before = self.diag_now()
        t0 = time.time_ns()
        self.monitor.send("latch")
        ok1, m1 = self._reply("latch", 60)
        # Put the empty scene back as the background: the fault ends when it is latched
        # and the object is in view again.
        self.player.send("mode background")
        self.wait(0.3)
        self.monitor.send("latch")
        ok2, m2 = self._reply("latch", 60)
        self.player.send("mode objects")
        t1 = time.time_ns()
        after = self.diag_after(t1 + 200_000_000)
        n = cnt(after, "latch_requests") - cnt(before, "latch_requests")
        f = cnt(after, "latched_frames") - cnt(before, "latched_frames")
        ok = n >= 2 and f >= 2 * self.a.background_frames
        self._fault("latch_in_view", p, t0, t1, {"diagnostics": {"latch_requests": n, "latched_frames": f, "ok": ok}},
                    note=f"in view: {'ok' if ok1 else 'failed'} ({m1}); empty scene again: {'ok' if ok2 else 'failed'} ({m2})")
        self.latches = getattr(self, "latches", 0) + 2

    def fault_parameters(self, p):
        before = self.diag_now()
        t0 = time.time_ns()
        self.monitor.send(f"param threshold_mm {p['threshold_mm']}")
        ok1, m1 = self._reply("param")
        self.wait(p["s"])
        self.monitor.send("param threshold_mm 30.0")
        ok2, m2 = self._reply("param")
        t1 = time.time_ns()
        after = self.diag_after(t1 + 200_000_000)
        n = cnt(after, "parameter_changes") - cnt(before, "parameter_changes")
        self._fault("parameters", p, t0, t1, {"diagnostics": {"parameter_changes": n, "ok": n >= 2 and ok1 and ok2}},
                    note=f"set: {ok1} {m1}; back: {ok2} {m2}")
        self.param_sets = getattr(self, "param_sets", 0) + 2

    def fault_camera_moved(self, p):
        before = self.diag_now()
        t0 = time.time_ns()
        self.player.send("mode moved")
        self.wait(p["s"])
        self.player.send("mode objects")
        t1 = time.time_ns()
        after = self.diag_after(t1 + 200_000_000)
        n = cnt(after, "camera_moves") - cnt(before, "camera_moves")
        self._fault("camera_moved", p, t0, t1, {"diagnostics": {"camera_moves": n, "ok": n >= 1}})
        self.moves = getattr(self, "moves", 0) + 1

    def finish(self, plan):
        self.wait(1.0)
        last_diag = self.diag_now()
        crashed = self.node.poll() is not None
        for peer in (self.player, self.monitor, self.reader):
            peer.stop()
        rc = None
        if not crashed:
            self.node.send_signal(signal.SIGINT)
            try:
                rc = self.node.wait(30)
            except subprocess.TimeoutExpired:
                self.node.kill()
                rc = self.node.wait()
        else:
            rc = self.node.returncode
        log = self.node_log.read_text(errors="replace")
        stats = json.loads(self.stats_json.read_text()) if self.stats_json.exists() else None
        with self.lock:
            outputs = [[st, arr, int(bool(self.masks.get(st)))] for st, arr in sorted(self.corrected.items())]
        injected = {
            "malformed": getattr(self, "malformed_total", 0),
            "burst": sum(1 for f in self.faults if f["kind"] == "burst"),
            "player_crash": getattr(self, "crashes", 0),
            "reader_stall": getattr(self, "stalls", 0),
            "latch_in_view": getattr(self, "latches", 0) + 1,
            "parameters": getattr(self, "param_sets", 0),
            "camera_moved": getattr(self, "moves", 0),
        }
        return {
            "path": self.path, "bag": str(self.bag), "size": self.a.size, "input_rate_hz": self.a.rate,
            "duration_s": self.a.duration, "warmup_s": self.a.warmup,
            "t_measure": self.t_measure, "t_end": self.t_end,
            "outputs": outputs, "samples": self.samples, "faults": self.faults,
            "skipped_faults": self.skipped, "injected": injected, "stats": stats,
            "diagnostics_at_end": last_diag, "crashed": crashed, "node_exit": rc,
            "panicked": "panicked" in log,
        }


def cnt(values, key):
    try:
        return int(values.get(key, 0))
    except ValueError:
        return 0


def analyse(raw, a):
    """The conditions over one path's raw record (what Run.finish returns), with the
    limits in `a`."""
    stats, crashed, rc = raw["stats"], raw["crashed"], raw["node_exit"]
    t_measure, t_end = raw["t_measure"], raw["t_end"]
    t_measure_ns = int(t_measure * 1e9)
    t_end_ns = int(t_end * 1e9)
    faults = [dict(f) for f in raw["faults"]]
    excluded = [(f["start_ns"], f["end_ns"] + 1_000_000_000) for f in faults]

    def clean(t):
        return not any(s <= t <= e for s, e in excluded)

    outputs = [(st, arr) for st, arr, _ in raw["outputs"]]
    masks = {st: bool(m) for st, _, m in raw["outputs"]}
    lat = [(s, (arr - s) / 1e6) for s, arr in outputs]
    # Windows over the measured time: six, at least a.min_window s each.
    span = (t_end_ns - t_measure_ns) / 1e9
    n_win = max(1, min(6, int(span // a.min_window)))
    w_ns = (t_end_ns - t_measure_ns) / n_win
    windows = []
    for i in range(n_win):
        w0, w1 = t_measure_ns + i * w_ns, t_measure_ns + (i + 1) * w_ns
        xs = [ms for s, ms in lat if w0 <= s < w1 and clean(s)]
        # Clean seconds of the window: its length less what the faults' periods cover.
        cover = 0.0
        for s, e in excluded:
            cover += max(0.0, min(e, w1) - max(s, w0))
        clean_s = (w1 - w0 - cover) / 1e9
        med, p99 = percentile(xs, 50), percentile(xs, 99)
        windows.append({
            "start_s": round((w0 - t_measure_ns) / 1e9, 1), "end_s": round((w1 - t_measure_ns) / 1e9, 1),
            "clean_s": round(clean_s, 1), "outputs": len(xs),
            "rate_hz": round(len(xs) / clean_s, 3) if clean_s > 0 else None,
            "latency_ms_median": round(med, 2), "latency_ms_p99": round(p99, 2),
            "p99_over_median": round(p99 / med, 3) if med > 0 else None,
        })
    # Memory: the median over a.rss_span s right after the warm-up, and at the end.
    ss = raw["samples"]
    rss_span = min(a.rss_span, span / 4)
    after_warm = [s["rss_kb"] for s in ss if t_measure <= s["t"] < t_measure + rss_span]
    at_end = [s["rss_kb"] for s in ss if t_end - rss_span <= s["t"] <= t_end]
    rss0, rss1 = percentile(after_warm, 50), percentile(at_end, 50)
    cpu = [s["cpu_pct"] for s in ss if s["t"] >= t_measure]
    # Resumed: the first corrected frame (non-empty mask) stamped after each fault's end.
    for f in faults:
        during = sum(1 for s, _ in outputs if f["start_ns"] <= s < f["end_ns"])
        f["outputs_per_s_during"] = round(during / max(1e-9, (f["end_ns"] - f["start_ns"]) / 1e9), 2)
        later = [(s, arr) for s, arr in outputs if s >= f["end_ns"] and masks.get(s)]
        f["resumed_after_s"] = round((later[0][1] - f["end_ns"]) / 1e9, 3) if later else None
    # The node's own stats at exit.
    inj = raw["injected"]
    st = stats or {}
    dropped = st.get("dropped", {})
    totals = {
        "malformed": ("dropped malformed + oversized + bad_image + size_mismatch",
                      sum(dropped.get(k, 0) for k in ["malformed", "oversized", "bad_image", "size_mismatch"])),
        "burst": ("dropped queue_full", dropped.get("queue_full", 0)),
        "player_crash": ("input_gaps", st.get("input_gaps", 0)),
        "reader_stall": ("publish_failures", st.get("publish_failures", 0)),
        "latch_in_view": ("services[0] (latch requests, the first latch included)", (st.get("services") or [0])[0]),
        "parameters": ("parameter_changes", st.get("parameter_changes", 0)),
        "camera_moved": ("camera_moves", st.get("camera_moves", 0)),
    }
    totals = {k: (key, have, inj[k]) for k, (key, have) in totals.items()}
    failures = []

    def fail(cond, text):
        failures.append({"condition": cond, "message": f"{raw['path']}: {text}"})

    if not (math.isfinite(rss0) and math.isfinite(rss1)):
        fail("rss", "no memory samples after the warm-up or at the end")
    elif abs(rss1 - rss0) > a.rss_tolerance * rss0:
        fail("rss", f"resident memory {rss0 / 1024:.1f} MB after the warm-up, {rss1 / 1024:.1f} MB at the end: "
                    f"{100 * (rss1 - rss0) / rss0:+.1f} % (limit ±{100 * a.rss_tolerance:.0f} %)")
    for i, w in enumerate(windows):
        if w["outputs"] < 10:
            fail("latency", f"window {i + 1}: {w['outputs']} outputs outside the faults, too few to measure")
        elif w["p99_over_median"] is None or w["p99_over_median"] > a.p99_ratio:
            fail("latency", f"window {i + 1} ({w['start_s']:.0f}-{w['end_s']:.0f} s): p99 latency "
                            f"{w['latency_ms_p99']:.1f} ms is {w['p99_over_median']}x the median "
                            f"{w['latency_ms_median']:.1f} ms (limit {a.p99_ratio}x)")
    rates = [w["rate_hz"] for w in windows if w["rate_hz"]]
    mean_rate = sum(rates) / len(rates) if rates else 0.0
    for i, w in enumerate(windows):
        if mean_rate and w["rate_hz"] is not None and abs(w["rate_hz"] - mean_rate) > a.rate_tolerance * mean_rate:
            fail("rate", f"window {i + 1}: {w['rate_hz']:.2f} outputs/s against the windows' mean {mean_rate:.2f}: "
                         f"{100 * (w['rate_hz'] - mean_rate) / mean_rate:+.1f} % (limit ±{100 * a.rate_tolerance:.0f} %)")
    for f in faults:
        d = f["counted"]["diagnostics"]
        if not d["ok"]:
            fail("counted", f"{f['kind']} at {(f['start_ns'] - t_measure_ns) / 1e9:.0f} s not counted in "
                            f"/diagnostics: {json.dumps({k: v for k, v in d.items() if k != 'ok'})}"
                            + (f" ({f['note']})" if f["note"] else ""))
        ra = f["resumed_after_s"]
        if ra is None or ra > a.resume_s:
            fail("resumed", f"{f['kind']} at {(f['start_ns'] - t_measure_ns) / 1e9:.0f} s: "
                            + ("no corrected frame after its end" if ra is None else
                               f"the first corrected frame {ra:.2f} s after its end (limit {a.resume_s} s)"))
    if stats is None:
        fail("counted", "the node wrote no --stats-json")
    else:
        for kind, (key, have, want) in totals.items():
            if want and have < want:
                fail("counted", f"{kind}: the node's stats count {have} ({key}) for {want} injected")
    if crashed or rc != 0 or raw["panicked"]:
        fail("no_crash", f"the node {'died during the run' if crashed else 'exited'} with {rc}"
                         + ("; a panic in its log" if raw["panicked"] else ""))
    n_out = sum(1 for s, _ in outputs if t_measure_ns <= s <= t_end_ns)
    return {
        "path": raw["path"], "bag": raw["bag"], "size": raw["size"],
        "duration_s": raw["duration_s"], "warmup_s": raw["warmup_s"], "window_s": round(w_ns / 1e9, 1),
        "input_rate_hz": raw["input_rate_hz"],
        "outputs": n_out,
        "output_rate_hz": round(n_out / span, 3) if span > 0 else None,
        "rss_kb_after_warmup": rss0, "rss_kb_at_end": rss1, "rss_span_s": round(rss_span, 1),
        "rss_change_pct": round(100 * (rss1 - rss0) / rss0, 2) if rss0 else None,
        "rss_kb_max": max((s["rss_kb"] for s in ss), default=None),
        "cpu_pct_mean": round(sum(cpu) / len(cpu), 1) if cpu else None,
        "latency_ms_median": round(percentile([ms for s, ms in lat if clean(s)], 50), 2),
        "latency_ms_p99": round(percentile([ms for s, ms in lat if clean(s)], 99), 2),
        "windows": windows,
        "faults": [dict(f, start_s=round((f["start_ns"] - t_measure_ns) / 1e9, 2),
                        end_s=round((f["end_ns"] - t_measure_ns) / 1e9, 2)) for f in faults],
        "faults_not_injected": raw["skipped_faults"],
        "node_stats_counted": {k: {"counter": key, "node": have, "injected": want} for k, (key, have, want) in totals.items()},
        "diagnostics_at_end": raw["diagnostics_at_end"],
        "node_exit": rc,
        "failures": failures,
        "series": {
            "t_s": [round(s["t"] - t_measure, 2) for s in ss],
            "rss_kb": [s["rss_kb"] for s in ss],
            "cpu_pct": [s["cpu_pct"] for s in ss],
            "latency": [[round((s - t_measure_ns) / 1e9, 3), round(ms, 2)] for s, ms in lat],
        },
    }


def plot(reports, path):
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return "matplotlib is not installed (bash scripts/setup-python.sh installs it): no plot"
    fig, axes = plt.subplots(3, len(reports), figsize=(6.5 * len(reports), 8), sharex="col", squeeze=False)
    for j, rep in enumerate(reports):
        s = rep["series"]
        ax = axes[0][j]
        ax.plot(s["t_s"], [k / 1024 for k in s["rss_kb"]], lw=1)
        ax.set_ylabel("resident MB")
        ax.set_title(f"{rep['path']}: {rep['duration_s'] / 60:.0f} min at {rep['input_rate_hz']:.0f} Hz in")
        ax = axes[1][j]
        if s["latency"]:
            xs, ys = zip(*s["latency"])
            ax.plot(xs, ys, ",", alpha=0.6)
        ax.set_ylabel("latency ms (stamp to output)")
        ax.set_yscale("log")
        ax = axes[2][j]
        for w in rep["windows"]:
            ax.hlines(w["rate_hz"] or 0, w["start_s"], w["end_s"], color="C2")
        ax.set_ylabel("outputs/s per window")
        ax.set_xlabel("s after the warm-up")
        for row in axes:
            for f in rep["faults"]:
                row[j].axvspan(f["start_s"], f["end_s"] + 1, color="C3", alpha=0.15, lw=0)
            row[j].axvline(0, color="k", lw=0.5)
    axes[0][0].text(0.01, 0.02, "shaded: a fault's period and 1 s after", transform=axes[0][0].transAxes, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    return None


def prepare_bag(a, path, out):
    """The bundled document holder rendered at --size (with phasors at three frequencies for
    the multi-frequency path), once, by the node's own simulator."""
    w, h = a.size.split("x")
    name = f"{'sf' if path == 'single_frequency' else 'mf'}_{w}x{h}"
    bag = out / f"{name}.mcap"
    if bag.exists():
        return bag
    scene = (REPO / "bags" / "document_holder.toml").read_text()
    scene += f"\n[camera]\nwidth = {int(w)}\nheight = {int(h)}\n"
    if path == "multi_frequency":
        scene += "modulation_frequencies_hz = [20e6, 50e6, 100e6]\n"
    toml = out / f"{name}.toml"
    toml.write_text(scene)
    subprocess.run([a.node, "simulate", str(toml), "-o", str(bag)], check=True, stdout=subprocess.DEVNULL)
    return bag


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=duration, default=duration("15m"),
                    help="each path's length after the first latch, warm-up included (90s, 15m, 1h)")
    ap.add_argument("--paths", default="single_frequency,multi_frequency")
    ap.add_argument("--size", default="640x480", help="the recording's size, WxH")
    ap.add_argument("--seed", type=int, default=54)
    ap.add_argument("--node", help="the node's binary")
    ap.add_argument("--out", type=Path, default=REPO / "out" / "soak")
    ap.add_argument("--json", type=Path, help="also write the report here, and print no progress")
    ap.add_argument("--rate", type=float, default=30.0, help="input rate, Hz")
    ap.add_argument("--xi", default="0.65", help="a fixed xi for the node, or `estimate`")
    ap.add_argument("--background-frames", type=int, default=10)
    ap.add_argument("--warmup", type=duration, help="default 5 %% of the duration, 15 s to 2 min")
    ap.add_argument("--gap", type=float, default=30.0, help="least time between faults, s")
    ap.add_argument("--skip", action="append", default=[], metavar="[PATH:]KIND",
                    help="a fault not to inject (on PATH only); the report lists it")
    ap.add_argument("--recheck", action="store_true",
                    help="no run: check the raw records a run left in --out again, with these limits")
    ap.add_argument("--min-window", type=float, default=30.0)
    ap.add_argument("--rss-span", type=float, default=30.0,
                    help="s of memory samples whose median is compared (at most a quarter of the measured time)")
    ap.add_argument("--rss-tolerance", type=float, default=0.05)
    ap.add_argument("--p99-ratio", type=float, default=2.0)
    ap.add_argument("--rate-tolerance", type=float, default=0.05)
    ap.add_argument("--resume-s", type=float, default=1.0)
    a = ap.parse_args()
    if a.warmup is None:
        a.warmup = min(120.0, max(15.0, 0.05 * a.duration))
    a.out.mkdir(parents=True, exist_ok=True)
    progress = Progress(a.json is not None)
    raws = []
    for path in a.paths.split(","):
        if path not in ("single_frequency", "multi_frequency"):
            raise SystemExit(f"--paths: {path!r} is neither single_frequency nor multi_frequency")
        raw_file = a.out / f"{path}.raw.json"
        if a.recheck:
            if raw_file.exists():
                raws.append(json.loads(raw_file.read_text()))
            continue
        if not a.node:
            raise SystemExit("--node: the node's binary is needed for a run")
        bag = prepare_bag(a, path, a.out)
        progress.line(f"{path}: starting", force=True)
        run = Run(a, path, bag, a.out, progress)
        try:
            raws.append(run.run())
        finally:
            for name in ("player", "monitor", "reader"):
                peer = getattr(run, name, None)
                if peer is not None and peer.p.poll() is None:
                    peer.p.kill()
            if getattr(run, "node", None) is not None and run.node.poll() is None:
                run.node.kill()
        raw_file.write_text(json.dumps(raws[-1]))
        progress.done()
    if not raws:
        raise SystemExit(f"--recheck: no raw record (PATH.raw.json) in {a.out}")
    reports = [analyse(raw, a) for raw in raws]
    png = a.out / "soak.png"
    why = plot(reports, png)
    report = {
        "command": " ".join(sys.argv[1:]),
        "seed": a.seed,
        "conditions": {"rss_tolerance": a.rss_tolerance, "p99_ratio": a.p99_ratio,
                       "rate_tolerance": a.rate_tolerance, "resume_s": a.resume_s,
                       "min_window_s": a.min_window, "rss_span_s": a.rss_span},
        "plot": None if why else str(png),
        "paths": reports,
        "failures": [f for r in reports for f in r["failures"]],
    }
    (a.out / "soak.json").write_text(json.dumps(report, indent=1))
    if a.json:
        a.json.write_text(json.dumps(report, indent=1))
    else:
        for r in reports:
            print(f"{r['path']} ({r['size']}): {r['outputs']} outputs ({r['output_rate_hz']} /s from "
                  f"{r['input_rate_hz']:.0f} Hz in), RSS {r['rss_kb_after_warmup'] / 1024:.1f} -> "
                  f"{r['rss_kb_at_end'] / 1024:.1f} MB ({r['rss_change_pct']:+.2f} %), latency median "
                  f"{r['latency_ms_median']} ms, p99 {r['latency_ms_p99']} ms, CPU {r['cpu_pct_mean']} %, "
                  f"{len(r['faults'])} faults" + (f" (not injected: {', '.join(r['faults_not_injected'])})"
                                                  if r["faults_not_injected"] else ""))
            for w in r["windows"]:
                print(f"  {w['start_s']:6.0f}-{w['end_s']:<6.0f} s: {w['outputs']:5d} outputs in {w['clean_s']:.0f} clean s "
                      f"({w['rate_hz']} /s), latency median {w['latency_ms_median']} ms, p99 {w['latency_ms_p99']} ms "
                      f"({w['p99_over_median']}x)")
            for f in r["faults"]:
                print(f"  {f['kind']:14s} at {f['start_s']:7.1f}-{f['end_s']:<7.1f} s: counted "
                      f"{json.dumps({k: v for k, v in f['counted']['diagnostics'].items() if k != 'ok'})}, "
                      f"resumed after {f['resumed_after_s']} s, {f['outputs_per_s_during']} outputs/s during it")
        print(f"report: {a.out / 'soak.json'}; " + (why or f"plot: {png}"))
    for f in report["failures"]:
        print(f"FAIL {f['condition']}: {f['message']}", file=sys.stderr)
    if not report["failures"] and not a.json:
        print("every condition held")
    return 1 if report["failures"] else 0


if __name__ == "__main__":
    sys.exit(main())
