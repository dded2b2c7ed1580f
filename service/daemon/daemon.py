"""The estimator service: CAN in → decode → PackEstimator → CAN + Zenoh out (DESIGN §1, §6).

One asyncio loop runs these tasks:

- **receive** (:class:`~service.daemon.can_rx.CanReceiver`): every frame goes through
  :class:`service.bus.decoder.FrameDecoder`; each :class:`PackSample` it completes steps the
  estimator with ``dt`` from the sample timestamps: the frames' own, or with
  ``mapping.time_signal`` the sender's sample time from the time-sync frame (a replay faster
  than real time onto a kernel bus, which stamps frames on arrival).  Cells that are not ``fresh`` are
  passed as inactive (no voltage update) and published as stale, never extrapolated as if
  measured.  A non-positive ``dt`` is skipped and counted; a gap longer than
  :data:`MAX_STEP_S` under load cannot be integrated honestly (the current during it is
  unknown), so the cells restart from OCV with a large covariance, counted and flagged
  ``ocv_init``; a gap with the pack at rest at both ends is integrated (and counted).
- **CAN output** every ``output.can_period_s``: :class:`service.bus.encoder.OutputEncoder`
  frames sent with ``timeout=0`` in small paced chunks; failures are counted, never awaited.
- **Zenoh output**: after every sample that changed the estimate, an *estimate* round (the
  SOC of the cells it moved, the summary with the pack view) handed to
  :class:`~service.daemon.zenoh_pub.ZenohPublisher` (bounded queue, own thread, each key
  rate-limited to ``output.min_publish_interval_s``), so a change reaches a dashboard within
  milliseconds; and every ``output.zenoh_period_s`` a *full* round (parameters, health, and
  the SOC keys no estimate refreshed, which carries cells that went stale because samples stopped).
  Building a round is a copy of a few arrays on the loop; JSON and ``put`` happen on the
  publisher's thread, so a slow or absent Zenoh never blocks estimation.
- **slow identifier** every :data:`SLOW_PERIOD_S` of *sample* time, on the estimation path, so a
  replay at any speed (or an in-process feed) identifies exactly as a real-time run does.
- **checkpoint** every ``checkpoint.interval_s`` (file I/O in an executor) and once more on
  SIGTERM/SIGINT before a clean shutdown.

On start the checkpoint is restored if it is valid and matches (n_cells, cell profile);
otherwise the reason is logged, put in the health payload, and each cell starts from OCV
with σ = ``estimator.soc_init_std`` at the first sample where its own inputs are fresh
(flag ``ocv_init``, plus ``checkpoint_corrupt`` when the file was damaged).  Start-up is
clocked by samples, never by wall time, so a replay faster than real time loses nothing,
and a cell that is invalid from the start does not hold the others back.

A restored state is only as good as its age: the checkpoint's frame time is compared with
the first new sample.  Past ``checkpoint.max_age_s`` the pack may have moved while the
daemon was down, so every cell's SOC σ is widened by ``checkpoint.aged_c_rate`` × age (in
hours of 1 C) and its polarisation branches' σ to what that current would hold; if the age
cannot be known (the new timeline is more than ``max_age_s`` before the checkpoint, or the
checkpoint has no time), the cells restart from OCV.  Either way ``state_aged`` is raised.  A sample marked ``reanchored`` by the decoder (its clock jumped) is not
integrated: the time since the previous sample is unknown.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import signal
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can
import numpy as np

from service.bus.types import PackSample, PackSnapshot
from service.cell.profile import FIT_TEMPERATURE_MARGIN_K, CellProfile, load_profile
from service.daemon.can_rx import CanReceiver, ReceiverClosed
from service.daemon.checkpoint import (
    checkpoint_write_problem,
    load_checkpoint,
    profile_hash,
    save_checkpoint,
)
from service.daemon.health import HealthMonitor, wall_time_of
from service.daemon.zenoh_pub import PublishRound, ZenohPublisher
from service.estimators.pack_view import OcvEnergy, PackView, pack_view
from service.estimators.state_of_health import CellHealth

log = logging.getLogger(__name__)

#: longest sample interval the estimator integrates under load; a longer gap restarts the
#: cells from OCV unless the pack was at rest (|I| <= REST_C_RATE · C) at both ends of it
MAX_STEP_S = 10.0
REST_C_RATE = 0.05
#: the service reads its sample period as the median of this many first intervals
PERIOD_INTERVALS = 16
#: period of the slow identifier, in sample time
SLOW_PERIOD_S = 1.0
#: an OCV start counts as converged once every cell's SOC σ is below this
OCV_CONVERGED_STD = 0.03
#: the receive loop yields to other tasks at least this often while it has a backlog
RX_YIELD_S = 0.005
#: the interpreter's thread switch interval while the service runs (Python's default is 5 ms):
#: the receive thread, the Zenoh publisher and the loop hand the GIL to each other at every
#: sample, and a thread that wants it waits up to this long for a busy one to let go
GIL_SWITCH_INTERVAL_S = 0.001
#: CAN output: frames sent back to back before yielding
CAN_TX_CHUNK = 8
CAN_TX_GAP_S = 0.001


class Daemon:
    """The whole service for one pack.  ``bus`` (optional) is owned by the caller.

    Without ``bus`` the daemon opens ``can.Bus(**config.bus.bus_kwargs())`` itself and
    re-creates it after bus errors.  ``profile``, ``estimator`` and
    ``zenoh_session_factory`` may be injected (tests, the demo).
    """

    def __init__(
        self,
        config: Any,
        bus: can.BusABC | None = None,
        *,
        profile: CellProfile | None = None,
        estimator: Any | None = None,
        zenoh_session_factory: Callable[[], Any] | None = None,
        install_signal_handlers: bool = True,
    ) -> None:
        from service.bus.decoder import FrameDecoder
        from service.estimators.pipeline import PackEstimator

        self.config = config
        self.n = int(config.pack.n_cells)
        self.profile = profile if profile is not None else load_profile(config.cell_profile)
        self.profile_sha256 = profile_hash(self.profile)
        self.health = HealthMonitor(pack=config.zenoh.pack_id)
        self.decoder = FrameDecoder(config)
        self.encoder = None
        if config.output.can_enabled:
            from service.bus.encoder import OutputEncoder

            self.encoder = OutputEncoder(config)
        self.estimator = estimator if estimator is not None else PackEstimator(
            self.profile, self.n, config.estimator, sample_period_s=config.estimator.sample_period_s)
        #: the first sample intervals, until the sample period is known (the G-L memory's span
        #: in samples follows it: PackEstimator.set_sample_period); known when the config sets it
        self._intervals: list[float] = []
        self._period_known = config.estimator.sample_period_s is not None
        b = config.bus
        if bus is not None:
            self.receiver = CanReceiver(self.health, bus=bus, reconnect_initial_s=b.reconnect_initial_s,
                                        reconnect_max_s=b.reconnect_max_s)
        else:
            from service.daemon.bus_open import BusOpener

            self.receiver = CanReceiver(self.health, open_bus=BusOpener(b),
                                        reconnect_initial_s=b.reconnect_initial_s, reconnect_max_s=b.reconnect_max_s)
        self.publisher: ZenohPublisher | None = None
        if config.output.zenoh_enabled:
            self.publisher = ZenohPublisher(config.zenoh, config.output.queue_size, self.health,
                                            session_factory=zenoh_session_factory,
                                            min_interval_s=config.output.min_publish_interval_s)
        self._install_signals = install_signal_handlers
        self.metrics = None
        metrics_cfg = getattr(config, "metrics", None)
        if metrics_cfg is not None and metrics_cfg.enabled:
            from service.daemon.metrics import MetricsServer

            self.metrics = MetricsServer(self.counters, self.health.flags, self.health.uptime_s, self.n,
                                         host=metrics_cfg.host, port=metrics_cfg.port)
            self.metrics.attach(self.health)

        self._ocv_energy = OcvEnergy(self.profile.ocv_table())
        # estimation state
        self.initialised = False
        #: bumped whenever the estimate changed (a step, a start from OCV): it is then published
        self._est_seq = 0
        self._stale_published = np.ones(self.n, dtype=bool)
        self.restored = False
        self._last_t: float | None = None
        self._last_sample: PackSample | None = None
        self._beyond_fit_logged = False  # temperature_beyond_fit was raised at the last status
        self._last_sample_mono: float | None = None
        self._last_frame_wall: float | None = None
        self._fresh = np.zeros(self.n, dtype=bool)
        #: cells started (from OCV or a checkpoint); a cell starts at its first fresh sample
        self._cell_started = np.zeros(self.n, dtype=bool)
        #: frame time of the restored checkpoint's last sample (None: no time in it)
        self._restored_t_s: float | None = None
        self._state_aged = False
        self._resets_seen = 0
        self._prev_current: float | None = None
        self._ckpt_seq = 0
        self._ckpt_saved_seq = 0
        self._ckpt_lock = threading.Lock()
        self.samples = 0
        self.steps = 0
        #: whether the checkpoint written when the run ended was saved (None while running)
        self.final_checkpoint_saved: bool | None = None
        self._slow_due_t: float | None = None
        self.step_time_s = 0.0
        self.can_frames_out = 0
        self.stopping = False
        self._started = asyncio.Event()
        #: called as ``fn(sample)`` after every estimator step (the demo scores with it)
        self.step_listeners: list[Callable[[PackSample], None]] = []

    # -- lifecycle ---------------------------------------------------------------------
    async def run(self, stop: asyncio.Event | None = None) -> None:
        """Run until ``stop`` is set or SIGTERM/SIGINT; then a final checkpoint and a clean exit.
        While it runs the process's thread switch interval is :data:`GIL_SWITCH_INTERVAL_S`."""
        switch_interval = sys.getswitchinterval()
        sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
        try:
            await self._run(stop)
        finally:
            sys.setswitchinterval(switch_interval)

    async def _run(self, stop: asyncio.Event | None) -> None:
        stop = stop or asyncio.Event()
        loop = asyncio.get_running_loop()
        installed = self._add_signal_handlers(loop, stop) if self._install_signals else []
        self.restore()
        if self.metrics is not None:
            self.metrics.start()
        if self.publisher is not None:
            self.publisher.start()
        tasks = {
            asyncio.create_task(self._rx_loop(), name="socd-rx"),
            asyncio.create_task(self._periodic(self.config.checkpoint.interval_s, self._checkpoint_async),
                                name="socd-checkpoint"),
        }
        if self.encoder is not None:
            tasks.add(asyncio.create_task(self._periodic(self.config.output.can_period_s, self._can_output),
                                          name="socd-can-out"))
        if self.publisher is not None:
            tasks.add(asyncio.create_task(self._periodic(self.config.output.zenoh_period_s, self._zenoh_output),
                                          name="socd-zenoh-out"))
        stop_task = asyncio.create_task(stop.wait(), name="socd-stop")
        self._started.set()
        log.info(
            "socd running: %d cells, bus %s:%s, clock %s, zenoh %s, checkpoint %s (%s)",
            self.n, self.config.bus.interface, self.config.bus.channel,
            self.config.mapping.time_signal or "frame timestamps",
            ",".join(self.config.zenoh.listen) if self.publisher is not None else "off",
            self.config.checkpoint.path, self.health.checkpoint_state,
        )
        crashed: BaseException | None = None
        try:
            done, _ = await asyncio.wait(tasks | {stop_task}, return_when=asyncio.FIRST_COMPLETED)
            for t in done:
                if t is not stop_task and not t.cancelled() and t.exception() is not None:
                    crashed = t.exception()
                    log.critical("task %s crashed: %r", t.get_name(), crashed)
        finally:
            self.stopping = True
            for t in tasks | {stop_task}:
                t.cancel()
            await asyncio.gather(*tasks, stop_task, return_exceptions=True)
            self.final_checkpoint_saved = self.save_checkpoint()
            if self.publisher is not None:
                self.publisher.stop()
            self.receiver.close()
            if self.metrics is not None:
                self.metrics.stop()
            for sig in installed:
                loop.remove_signal_handler(sig)
        if crashed is not None:
            raise crashed

    @staticmethod
    def _add_signal_handlers(loop: asyncio.AbstractEventLoop, stop: asyncio.Event) -> list[int]:
        installed = []
        for sig in (signal.SIGTERM, signal.SIGINT):
            try:
                loop.add_signal_handler(sig, stop.set)
                installed.append(sig)
            except (NotImplementedError, RuntimeError, ValueError):
                pass  # not the main thread, or a platform without signals
        return installed

    async def wait_started(self) -> None:
        await self._started.wait()

    async def _periodic(self, period_s: float, fn: Callable[[], Any]) -> None:
        loop = asyncio.get_running_loop()
        next_at = loop.time() + period_s
        while True:
            await asyncio.sleep(max(0.0, next_at - loop.time()))
            next_at = max(next_at + period_s, loop.time())
            try:
                res = fn()
                if asyncio.iscoroutine(res):
                    await res
            except asyncio.CancelledError:
                raise
            except Exception:  # one bad round must not stop the service
                self.health.count("internal_errors")
                log.exception("periodic task %s failed", getattr(fn, "__name__", fn))

    # -- checkpoint --------------------------------------------------------------------
    def restore(self) -> str:
        """Load the checkpoint if it is usable; return the outcome ("restored" or a reason)."""
        path = Path(self.config.checkpoint.path)
        if (problem := checkpoint_write_problem(path)) is not None:
            # the service still estimates and publishes; only its state will not survive a restart
            log.warning("%s; estimating without saving state (socd check reports it)", problem)
        res = load_checkpoint(path, n_cells=self.n, profile_sha256=self.profile_sha256)
        if res.ok:
            try:
                self.estimator.set_state(res.state)
            except (ValueError, KeyError, TypeError) as exc:
                res.reason, res.detail = "mismatch", f"{path}: state does not fit this estimator: {exc}"
        if res.ok:
            self.initialised = self.restored = True
            if self._period_known:  # the state holds the memory it was saved with: at the period set
                self._run_at_sample_period(self.config.estimator.sample_period_s)
            self._cell_started[:] = True
            t = res.meta.get("t_s")
            self._restored_t_s = float(t) if isinstance(t, (int, float)) and np.isfinite(t) else None
            self.health.set_flag("checkpoint_restored", True)
            self.health.count("checkpoint_restored")
            self.health.checkpoint_state = "restored"
            log.info("restored estimator state from %s (saved at frame time %s)", path, res.meta.get("t_s"))
            return "restored"
        self.health.checkpoint_state = f"{res.reason}: {res.detail}"
        self.health.count(f"checkpoint_{res.reason}")
        if res.reason == "corrupt":
            self.health.set_flag("checkpoint_corrupt", True)
        if res.reason in ("corrupt", "mismatch"):
            self._quarantine(path, res.reason)
        (log.info if res.reason == "missing" else log.warning)(
            "no usable checkpoint (%s); will start from OCV with a large covariance", res.detail)
        return res.reason

    def _quarantine(self, path: Path, reason: str) -> None:
        # Keep the evidence: the next save would overwrite it.  Only a file is moved: a folder
        # at the checkpoint path is never ours to rename (the config refuses one).
        if not path.is_file():
            return
        target = path.with_name(f"{path.name}.{reason}-{int(time.time())}")
        try:
            path.replace(target)
            log.warning("moved unusable checkpoint to %s", target)
        except OSError as exc:
            log.warning("could not move unusable checkpoint %s: %s", path, exc)

    def _checkpoint_args(self) -> dict | None:
        if not self.initialised:
            return None
        self._ckpt_seq += 1
        return {
            "seq": self._ckpt_seq,
            "path": self.config.checkpoint.path,
            "state": self.estimator.get_state(),
            "n_cells": self.n,
            "profile_sha256": self.profile_sha256,
            "t_s": self._last_t,
        }

    def save_checkpoint(self) -> bool:
        """Write a checkpoint now (blocking); False if there is nothing to save or it failed."""
        args = self._checkpoint_args()
        if args is None:
            return False
        return self._save(args)

    def _save(self, args: dict) -> bool:
        args = dict(args)
        seq = args.pop("seq")
        # A periodic save still running in the executor must not overwrite a newer state
        # (the final one on shutdown): saves are serialised and never go backwards.
        with self._ckpt_lock:
            if seq <= self._ckpt_saved_seq:
                return False
            try:
                save_checkpoint(**args)
            except (OSError, ValueError) as exc:
                self.health.count("checkpoint_write_failed")
                log.error("checkpoint write failed: %s", exc)
                return False
            self._ckpt_saved_seq = seq
        self.health.count("checkpoints_saved")
        self.health.set_flag("checkpoint_corrupt", False)
        return True

    async def _checkpoint_async(self) -> None:
        args = self._checkpoint_args()  # state copied on the loop, written off it
        if args is not None:
            await asyncio.get_running_loop().run_in_executor(None, self._save, args)

    # -- receive + estimate ------------------------------------------------------------------
    async def _rx_loop(self) -> None:
        last_yield = time.perf_counter()
        while True:
            try:
                msg = await self.receiver.recv()
            except ReceiverClosed:
                return
            arrival = time.time()
            try:
                samples = self.decoder.feed(msg)
                for s in samples:
                    self.on_sample(s, wall_time_of(msg.timestamp, arrival))
            except Exception:  # bad input must never stop the service
                self.health.count("internal_errors")
                log.exception("frame %s could not be processed", msg)
            now = time.perf_counter()
            if now - last_yield > RX_YIELD_S:
                # a non-empty queue returns without suspending: let timers and signals run
                await asyncio.sleep(0)
                last_yield = time.perf_counter()

    def on_sample(self, s: PackSample, frame_wall_s: float | None = None) -> None:
        """Advance the estimator by one decoded sample (the receive task calls this) and hand
        the new estimate to the Zenoh publisher when it changed."""
        seq = self._est_seq
        self._estimate(s, frame_wall_s)
        if self._est_seq != seq and self.publisher is not None:
            self.publisher.submit(self.estimate_round(np.asarray(s.fresh, dtype=bool)))

    def _estimate(self, s: PackSample, frame_wall_s: float | None) -> None:
        self.samples += 1
        mono = time.monotonic()
        fresh = np.asarray(s.fresh, dtype=bool)
        self._fresh = fresh
        self._last_sample = s
        self._last_sample_mono = mono
        if frame_wall_s is not None:
            self._last_frame_wall = frame_wall_s
        if not np.isfinite(s.current_a):
            self.health.count("sample_no_current")
            return
        if not self.initialised:
            self._try_initialise(s, fresh)
            return
        if self._last_t is None:  # first sample after a restore: nothing to integrate yet
            self._check_restored_age(s, fresh)
            self._last_t = s.t_s
            self._prev_current = float(s.current_a)
            return
        if s.reanchored and s.t_s <= self._last_t:
            # the input clock went back: the interval since the last sample is unknown
            self.health.count("clock_reanchored_back", flag="clock_reanchored")
            log.warning("input clock jumped back to %.3f s; continuing from there without integrating", s.t_s)
            self._last_t = s.t_s
            self._prev_current = float(s.current_a)
            return
        if s.reanchored:  # forward: handled as a gap (below), flagged
            self.health.count("clock_reanchored_forward", flag="clock_reanchored")
        late = fresh & ~self._cell_started
        if late.any():  # cells invalid until now: start them from their first fresh inputs
            self.estimator.initialise(self._filled(s.voltage_v, fresh), self._filled(s.temperature_c, fresh),
                                      s.current_a, cells=late)
            self._cell_started |= late
            self._est_seq += 1
            self.health.count("cells_started_late", int(late.sum()))
        dt = s.t_s - self._last_t
        if not np.isfinite(dt) or dt <= 0.0:
            self.health.count("dt_nonpositive")
            return
        self._last_t = s.t_s
        prev_current = self._prev_current
        self._prev_current = float(s.current_a)
        if dt > MAX_STEP_S and not self._resting(prev_current, s.current_a):
            self.health.count("dt_gap_reinit")
            log.warning("%.1f s without samples: restarting fresh cells from OCV", dt)
            if fresh.any():
                self.estimator.initialise(self._filled(s.voltage_v, fresh), self._filled(s.temperature_c, fresh),
                                          s.current_a, cells=fresh)
                self._est_seq += 1
            return
        if dt > MAX_STEP_S:
            self.health.count("dt_gap_at_rest")
        if not self._period_known:
            self._learn_sample_period(dt)
        t0 = time.perf_counter()
        self.estimator.step(dt, s.current_a, s.voltage_v, s.temperature_c, fresh)
        self.step_time_s += time.perf_counter() - t0
        self.steps += 1
        self._est_seq += 1
        self._after_step(s, fresh, frame_wall_s)
        for fn in self.step_listeners:
            fn(s)

    def _learn_sample_period(self, dt: float) -> None:
        """After :data:`PERIOD_INTERVALS` intervals, run the model at their median sample period."""
        self._intervals.append(dt)
        if len(self._intervals) < PERIOD_INTERVALS:
            return
        self._period_known = True
        self._run_at_sample_period(float(np.median(self._intervals)))

    def _run_at_sample_period(self, period_s: float) -> None:
        set_period = getattr(self.estimator, "set_sample_period", None)
        if set_period is not None:
            set_period(period_s)
            log.info("sample period %.3g s: G-L memory of %d samples", period_s, self.estimator.memory_length)

    def _resting(self, *currents: float | None) -> bool:
        """Both ends of a gap at rest: no charge moved in between, so it can be integrated."""
        limit = REST_C_RATE * float(self.profile.capacity_ah)
        return all(c is not None and np.isfinite(c) and abs(c) <= limit for c in currents)

    def _after_step(self, s: PackSample, fresh: np.ndarray, frame_wall_s: float | None) -> None:
        self._slow_identify(s.t_s)
        est = self.estimator
        resets = int(np.sum(est.reset_count))
        if resets > self._resets_seen:
            self.health.count("filter_resets", resets - self._resets_seen, flag="filter_reset")
            self.health.raise_flag("diverged")
            self._resets_seen = resets
        soc = est.soc
        bad = ~(np.isfinite(soc) & np.isfinite(est.soc_std))
        if bad.any():  # belt and braces: a NaN must never be published as a SOC
            self.health.count("nonfinite_estimate_reinit", int(bad.sum()), flag="filter_reset")
            cells = bad & fresh
            if cells.any():
                est.initialise(self._filled(s.voltage_v, fresh), self._filled(s.temperature_c, fresh),
                               s.current_a, cells=cells)
        if frame_wall_s is not None:
            self.health.record_latency("estimate", time.time() - frame_wall_s)

    def _check_restored_age(self, s: PackSample, fresh: np.ndarray) -> None:
        """Compare the restored state's time with the first new sample (see the module doc)."""
        ck = self.config.checkpoint
        age = None if self._restored_t_s is None else s.t_s - self._restored_t_s
        if age is not None and np.isfinite(age) and abs(age) <= ck.max_age_s:
            return  # recent (a slightly earlier first sample is frame-time jitter, not a new timeline)
        self.health.raise_flag("state_aged")
        self._state_aged = True
        widen = getattr(self.estimator, "widen_for_downtime", None)
        if age is not None and np.isfinite(age) and age > 0.0 and widen is not None:
            extra = widen(age, ck.aged_c_rate)  # SOC fraction the pack may have moved
            self.health.count("checkpoint_aged")
            log.warning("restored state is %.0f s old: SOC sigma widened by %.2f %%", age, 100 * extra)
            return
        self.health.count("checkpoint_age_unknown")
        log.warning("restored state's age is unknown (checkpoint time %s, first sample %.3f s): "
                    "restarting fresh cells from OCV", self._restored_t_s, s.t_s)
        if fresh.any():
            self.estimator.initialise(self._filled(s.voltage_v, fresh), self._filled(s.temperature_c, fresh),
                                      s.current_a, cells=fresh)
        self._cell_started = fresh.copy()

    def _try_initialise(self, s: PackSample, fresh: np.ndarray) -> None:
        """Start from OCV at the first sample with any fresh cell; the rest start when fresh."""
        if not fresh.any():
            self.health.count("init_waiting_for_cells")
            return
        v = self._filled(s.voltage_v, fresh)
        t = self._filled(s.temperature_c, fresh)
        self.estimator.initialise(v, t, s.current_a)
        self._cell_started = fresh.copy()
        self._resets_seen = int(np.sum(self.estimator.reset_count))
        self.initialised = True
        self._est_seq += 1
        self._last_t = s.t_s
        self._prev_current = float(s.current_a)
        self.health.count("ocv_init")
        log.info("started %d cells from OCV (%d without fresh inputs)", self.n, int((~fresh).sum()))

    @staticmethod
    def _filled(x: np.ndarray, fresh: np.ndarray) -> np.ndarray:
        """Values for cells without fresh inputs: the mean of the fresh ones (they stay stale)."""
        x = np.asarray(x, dtype=float)
        ok = fresh & np.isfinite(x)
        if ok.all():
            return x
        fill = float(np.mean(x[ok])) if ok.any() else 25.0
        return np.where(ok, x, fill)

    def _slow_identify(self, t_s: float) -> None:
        """The slow identifier once per :data:`SLOW_PERIOD_S` of sample time."""
        if self._slow_due_t is None or not np.isfinite(self._slow_due_t) or t_s < self._slow_due_t - SLOW_PERIOD_S:
            self._slow_due_t = t_s + SLOW_PERIOD_S  # first step, or the timeline moved back (re-anchored)
            return
        if t_s < self._slow_due_t or not self.steps:
            return
        self._slow_due_t = t_s + SLOW_PERIOD_S
        done = self.estimator.slow_update()
        if np.any(done):
            self.health.count("slow_updates")

    # -- outputs -------------------------------------------------------------------------
    def stale_mask(self) -> np.ndarray:
        """Cells whose inputs are not fresh; all of them when samples stopped arriving."""
        if self._last_sample_mono is None or time.monotonic() - self._last_sample_mono > self.config.mapping.stale_after_s:
            return np.ones(self.n, dtype=bool)
        return ~self._fresh

    def status_flags(self, stale: np.ndarray | None = None) -> dict[str, bool]:
        stale = self.stale_mask() if stale is None else stale
        self.health.absorb_decoder(self.decoder.counters)
        flags = self.health.flags()
        est = self.estimator
        flags["stale_cells"] = bool(stale.any())
        flags["no_current"] = (
            self._last_sample_mono is None
            or time.monotonic() - self._last_sample_mono > self.config.mapping.stale_after_s
        )
        ocv_started = np.asarray(getattr(est, "ocv_initialised", np.zeros(self.n, bool)), dtype=bool)
        # convergence is the filter's own σ; the σ published also holds what the filter does not model
        filter_std = np.asarray(getattr(est, "filter_soc_std", est.soc_std))
        flags["ocv_init"] = (not self.initialised and not self.restored) or bool(
            self.initialised and np.any(ocv_started & (filter_std > OCV_CONVERGED_STD))
        )
        # an aged restored state stays flagged until the filter has pulled every cell back in
        flags["state_aged"] = flags.get("state_aged", False) or (
            self._state_aged and bool(np.any(filter_std > OCV_CONVERGED_STD)))
        clamped = getattr(est, "param_clamped", None)
        flags["param_clamped"] = bool(np.any(clamped)) if clamped is not None else False
        flags["temperature_beyond_fit"] = self._temperature_beyond_fit(stale)
        if self.publisher is None:
            flags["zenoh_down"] = False
        for name in ("checkpoint_restored", "filter_reset", "bus_error", "zenoh_down", "publish_drops",
                     "diverged", "counter_errors", "decode_errors", "checkpoint_corrupt", "clock_reanchored",
                     "state_aged"):
            flags.setdefault(name, False)
        return flags

    def _temperature_beyond_fit(self, stale: np.ndarray) -> bool:
        """Whether a cell with fresh inputs reads a temperature the profile was not fitted near
        (:meth:`CellProfile.beyond_fit`); logged once each time it starts and stops."""
        s = self._last_sample
        beyond = (np.zeros(self.n, dtype=bool) if s is None
                  else self.profile.beyond_fit(s.temperature_c) & ~np.asarray(stale, dtype=bool))
        now = bool(beyond.any())
        if now and not self._beyond_fit_logged:
            fitted = sorted(p.temp_c for p in self.profile.parameters)
            log.warning("%d cell(s) read %.0f to %.0f °C, more than %g K outside the %g to %g °C the profile %r "
                        "was fitted at: their parameters are extrapolated and the SOC σ published does not allow "
                        "for that (status flag temperature_beyond_fit)", int(beyond.sum()),
                        float(np.min(s.temperature_c[beyond])), float(np.max(s.temperature_c[beyond])),
                        FIT_TEMPERATURE_MARGIN_K, fitted[0], fitted[-1], self.profile.name)
        elif not now and self._beyond_fit_logged:
            log.info("every cell reads within the profile's fitted temperatures again")
        self._beyond_fit_logged = now
        return now

    def pack_view(self) -> PackView | None:
        """The pack view (:mod:`service.estimators.pack_view`) over the started cells, with each
        cell's capacity as the estimator counts with it (its online estimate, or the profile's)
        and its last temperature; None before the first estimate."""
        if not self.initialised:
            return None
        s = self._last_sample
        temp = 25.0 if s is None else self._filled(s.temperature_c, np.isfinite(s.temperature_c))
        cap = getattr(self.estimator, "capacity_ah", None)  # an injected estimator may have none
        cap = np.full(self.n, float(self.profile.effective_capacity_ah)) if cap is None else np.asarray(cap, float)
        return pack_view(self.estimator.soc, cap, self._ocv_energy, temp, valid=self._cell_started)

    def snapshot(self) -> PackSnapshot:
        stale = self.stale_mask()
        flags = self.status_flags(stale)
        counters = self.health.all_counters(self.decoder.counters)
        est = self.estimator
        s = self._last_sample
        voltage = np.array(s.voltage_v, dtype=float) if s is not None else np.full(self.n, np.nan)
        return PackSnapshot(
            t_s=float(self._last_t if self._last_t is not None else (s.t_s if s is not None else 0.0)),
            soc=np.array(est.soc, dtype=float),
            soc_std=np.array(est.soc_std, dtype=float),
            voltage_v=voltage,
            params={k: np.array(v, dtype=float) for k, v in est.parameters().items()},
            stale=stale,
            status_flags=flags,
            counters={"frames_rejected": counters.get("frames_rejected", 0), "stale_cells": int(stale.sum())},
            pack=self.pack_view(),
            health=self._health_cells(),
        )

    def _health_cells(self) -> CellHealth | None:
        fn = getattr(self.estimator, "health", None)
        return fn().copy() if fn is not None else None

    async def _can_output(self) -> None:
        if self.encoder is None or not self.initialised:
            return
        # Frames are encoded chunk by chunk as they are sent: encoding a few hundred cells at once
        # would hold the loop (and the estimate of any sample arriving meanwhile) for milliseconds.
        frames = self.encoder.frames(self.snapshot())
        while chunk := list(itertools.islice(frames, CAN_TX_CHUNK)):
            for f in chunk:
                if self.receiver.send(f):
                    self.can_frames_out += 1
            await asyncio.sleep(CAN_TX_GAP_S)  # pace: a CAN tx queue is often only 10 frames deep
        self.health.counters["can_frames_out"] = self.can_frames_out

    def publish_round(self) -> PublishRound:
        snap = self.snapshot()
        flags = dict(snap.status_flags)
        est = self.estimator
        s = self._last_sample
        health = self.health.payload(snap.t_s, self.decoder.counters, flags)
        return PublishRound(
            t_s=snap.t_s,
            soc=snap.soc,
            soc_std=snap.soc_std,
            voltage_v=snap.voltage_v,
            stale=np.array(snap.stale, dtype=bool),
            params=snap.params,
            health=health,
            status_flags=flags,
            current_a=None if s is None else float(s.current_a),
            v_pred=np.array(est.v_pred, dtype=float),
            resets=np.array(est.reset_count, dtype=int),
            frame_wall_s=self._last_frame_wall if self.initialised else None,
            initialised=self.initialised,
            pack=snap.pack,
            health_cells=snap.health,
        )

    def estimate_round(self, fresh: np.ndarray) -> PublishRound:
        """The round published right after an estimate: the SOC keys of the cells it moved
        (fresh ones, and any whose stale state changed since the last such round) and the
        summary; no parameters or health (those go out with the full round)."""
        est = self.estimator
        s = self._last_sample
        stale = ~np.asarray(fresh, dtype=bool)
        cells = ~stale | (stale != self._stale_published)
        self._stale_published = stale
        return PublishRound(
            t_s=float(self._last_t if self._last_t is not None else (s.t_s if s is not None else 0.0)),
            soc=np.array(est.soc, dtype=float),
            soc_std=np.array(est.soc_std, dtype=float),
            voltage_v=np.array(s.voltage_v, dtype=float) if s is not None else np.full(self.n, np.nan),
            stale=stale,
            params={},
            health=None,
            status_flags=self.status_flags(stale),
            current_a=None if s is None else float(s.current_a),
            v_pred=np.array(est.v_pred, dtype=float),
            resets=np.array(est.reset_count, dtype=int),
            frame_wall_s=self._last_frame_wall,
            initialised=self.initialised,
            pack=self.pack_view(),
            full=False,
            cells=cells,
        )

    async def _zenoh_output(self) -> None:
        if self.publisher is not None:
            self.publisher.submit(self.publish_round())

    # -- figures for tools and tests --------------------------------------------------------
    def counters(self) -> dict[str, int]:
        out = self.health.all_counters(self.decoder.counters)
        out["can_frames_out"] = self.can_frames_out
        out["steps"] = self.steps
        out["samples"] = self.samples
        return out
