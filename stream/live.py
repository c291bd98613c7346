"""``adhoc-array live``: sound cards in, the enhanced stream out (a card and files), through the same stream
runner as replay (:func:`stream.run.run_stream`).

Each ``--input`` card records with its own clock (the ad-hoc problem); ``--output`` plays the enhanced
stream in real time; ``--record DIR`` keeps every raw input as a folder that ``adhoc-array replay DIR``
accepts unchanged. SIGINT (Ctrl-C) and SIGTERM end the stream: what was captured is processed and every
file is written and valid.
"""
from __future__ import annotations

import logging
import sys
import time
from pathlib import Path
from typing import Any, Sequence, TextIO

import numpy as np

from . import sinks
from .cards import CardPlayback, CardSource
from .config import EngineConfig, merge
from .run import RunOutcome, run_stream

log = logging.getLogger(__name__)

# sound cards we open start within milliseconds of each other: a short alignment window and search range
# (overridable) make the first output come after about 4.5 s instead of 12 s; a device that was quiet then is
# re-checked every 5 s
# live and network streams use replay's estimator, the tracker (since 2026-11-27: its underflows at 48 kHz came from
# the stream loop's stalls, now gone; it costs 12-16 % of a core here against 7-8 % for --estimator kalman: README)
LIVE_DEFAULTS = {"align_window_s": 4.0, "max_offset_s": 0.5, "align_recheck_s": 5.0,
                 "tracker_lookahead_s": 0.0}   # causal: the look-ahead's latency would break live's budget


class StatusLine:
    """A live status line: per-device level and clipping, overflow/underflow counts, per-device TOA and the
    tracked sources (with the seconds of speech so far in which no talker was steered), gated frames, CPU load
    and latency. On a terminal it rewrites one line; otherwise it prints a line every ``every_s`` seconds.
    """

    def __init__(self, source: CardSource, playback: CardPlayback | None = None, *, stream: TextIO | None = None,
                 every_s: float = 10.0) -> None:
        self.source = source
        self.playback = playback
        self.stream = stream or sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.every_s = every_s
        self._level = None
        self._t = (time.perf_counter(), time.process_time())
        self._last_print = 0.0
        self.last = ""

    def observe(self, frame) -> None:
        """Running level of each device (from the raw frames)."""
        n = len(self.source.active)
        if self._level is None:
            self._level = np.full(n, 1e-12)
        x = np.asarray(frame.samples, np.float32)
        if x.size:
            ms = float(np.dot(x.ravel(), x.ravel())) / x.size
            if ms == ms:   # NaN frames do not move the meter
                self._level[frame.device_id] = 0.7 * self._level[frame.device_id] + 0.3 * ms

    def text(self, pipeline) -> str:
        wall, cpu = time.perf_counter(), time.process_time()
        load = (cpu - self._t[1]) / max(wall - self._t[0], 1e-9)
        self._t = (wall, cpu)
        fs = pipeline.config.working_rate_hz
        ref = self.source.active[0]
        captured_s = ref.n_read_samples / ref.sample_rate_hz
        parts = [f"{captured_s:7.1f} s"]
        if not pipeline.aligner.ready:   # the first output comes once every device has filled the window
            need_s = (pipeline.aligner.window_samples / fs) + pipeline.aligner.max_offset_s
            parts[0] += f" (aligning the devices: first output after {need_s:.1f} s)"
        levels = 10 * np.log10(np.maximum(self._level, 1e-12)) if self._level is not None else []
        groups = pipeline.aligner.clock_groups   # one clock group per device (an array's mics: one group)
        first = sorted(set(groups))
        for d, (info, lvl) in enumerate(zip(self.source.active, levels)):
            clip = sum(c.counters.n_clipped_samples for c, g in zip(pipeline.conditioners, groups) if g == first[d])
            parts.append(f"{info.name} {lvl:4.0f} dBFS" + (f" clip {clip}" if clip else ""))
        n_ovf = sum(d.n_overflows for d in self.source.active)
        n_gap = sum(d.n_gaps for d in self.source.active)
        line = " | ".join(parts) + f" | overflows {n_ovf} gaps {n_gap}"
        if self.playback is not None:
            c = self.playback.counters()
            line += f" underflows {c['n_underflows']}"
        st = pipeline.state
        if len(st.toa_s):
            line += " | TOA ms " + " ".join(f"{1e3 * v:+.2f}" for v in st.toa_s[-1][1:])
        if pipeline.tracker is not None:
            tracks = [t for t in pipeline.tracker.tracks if t.kind != "tentative"]
            kinds = "".join("S" if t.kind == "speech" else "N" for t in tracks)
            unsteered_s, speech_s = pipeline.tracker.speech_seconds()
            line += (f" | sources {kinds or '-'} steered {pipeline.tracker.steered_id} "
                     f"(no talker in {unsteered_s:.1f} of {speech_s:.1f} s of speech)")
        line += f" | gated {pipeline.counters.n_gated} | CPU {100 * load:.0f}%"
        line += f" | latency ~{1e3 * self.latency_s(pipeline):.0f} ms"
        return line

    def latency_s(self, pipeline) -> float:
        """Input to output, estimated: the card buffers, one hop of framing, the beamformer's latency and what
        is queued for the output card."""
        fs = pipeline.config.working_rate_hz
        lat = (pipeline.latency_samples + pipeline.config.hop_samples) / fs
        lat += self.source.input_latency_s
        if self.playback is not None:
            lat += self.playback.queued_samples / self.playback.sample_rate_hz + self.playback.latency_s
        return lat

    def __call__(self, pipeline) -> None:
        self.last = self.text(pipeline)
        now = time.perf_counter()
        if self.tty:
            self.stream.write("\r\x1b[2K" + self.last[: 200])
            self.stream.flush()
        elif now - self._last_print >= self.every_s:
            self._last_print = now
            self.stream.write(self.last + "\n")
            self.stream.flush()

    def close(self) -> None:
        if self.tty and self.last:
            self.stream.write("\n")
            self.stream.flush()


def run_live(inputs: Sequence[str], out_dir: str | Path, *, output: str | None = None, record: str | Path | None = None,
             sample_rate_hz: float | None = None, block_samples: int = 0, config: EngineConfig | None = None,
             overrides: Sequence[tuple[dict[str, Any], str]] = (), names: Sequence[str] | None = None,
             status: bool | TextIO = True, stall_s: float = 1.0, max_duration_s: float | None = None,
             output_margin_s: float = 0.01, batch_s: float = 0.0, speech=None) -> RunOutcome:
    """Stream from sound cards until stopped (SIGINT/SIGTERM, or ``source.stop()``), writing every output.

    Parameters
    ----------
    inputs : sequence of str
        One ``--input`` spec per device (``NAME``, ``NAME:1,2``, or an index); the first is the reference.
    out_dir : path
        enhanced.wav, toa.csv, report.json and plots, as replay writes them.
    output : str, optional
        Card that plays the enhanced stream in real time.
    record : path, optional
        Folder for the raw inputs (replayable with ``adhoc-array replay``).
    sample_rate_hz : float, optional
        Open every card at this rate (default: each card's own default).
    block_samples : int
        PortAudio block size (0: the host's choice).
    status : bool or text stream
        The live status line (on stderr, or on the given stream).
    max_duration_s : float, optional
        Stop after the reference card has delivered this much audio (default: only a signal stops).
    output_margin_s : float
        Audio queued for the output card before it plays (:class:`~stream.cards.CardPlayback` ``queue_s``):
        a margin against hiccups of the stream loop, paid in latency; 0 for the lowest latency.
    batch_s : float
        Process the input in batches of this much audio (:class:`~stream.cards.CardSource` ``batch_s``): less
        CPU, that much more latency; 0 (default): every card period.
    """
    cfg = merge(config or EngineConfig(), LIVE_DEFAULTS, source="live defaults")
    for values, src in overrides:
        cfg = merge(cfg, values, source=src)
    source = CardSource(inputs, sample_rate_hz=sample_rate_hz, block_samples=block_samples, stall_s=stall_s,
                        names=names, max_duration_s=max_duration_s, batch_s=batch_s)
    state: dict[str, Any] = {}

    def on_frame(frame) -> None:
        if "recorder" not in state and record is not None:
            defaults = EngineConfig().as_dict()
            engine = {k: v for k, v in cfg.as_dict().items()
                      if v != defaults[k] and k not in ("plots", "progress", "speed", "block_s")}
            if engine.get("arrays"):   # the recording replays from any folder
                engine["arrays"] = str(Path(engine["arrays"]).resolve())
            state["recorder"] = sinks.RecordingSink(record, source.active, engine=engine,
                                                    description=f"adhoc-array live --input {' --input '.join(inputs)}")
        if record is not None:
            state["recorder"].write(frame)
        if "status" in state:
            state["status"].observe(frame)

    class Playback:   # the output card as a hop sink, opened on the first hop (the working rate is known then)
        def write(self, result) -> None:
            if "playback" not in state:
                fs = source.active[0].sample_rate_hz if cfg.working_rate_hz is None else cfg.working_rate_hz
                state["playback"] = CardPlayback(output, sample_rate_hz=fs, block_samples=block_samples,
                                                 queue_s=output_margin_s)
            state["playback"].write(result)

        def close(self) -> None:   # closed with the report (extra below), after the stream
            pass

    if status:   # from the first frame on, so that the levels are there at the first line
        state["status"] = StatusLine(source, None, stream=None if status is True else status)

    def status_cb(pipeline) -> None:
        state["status"].playback = state.get("playback")
        state["status"](pipeline)

    def extra(report: dict) -> None:
        for key in ("playback", "recorder", "status"):
            obj = state.get(key)
            if obj is not None:
                try:
                    obj.close()
                except Exception as err:  # noqa: BLE001 - closing must not lose the report
                    log.warning("Closing the %s failed (%s: %s).", key, type(err).__name__, err)
        cards = {"inputs": [{"name": d.name, "card": d.card, "channels": d.channels,
                             "sample_rate_hz": d.sample_rate_hz, "n_overflows": d.n_overflows,
                             "overflows_s": d.overflows_s,
                             "n_gaps": d.n_gaps, "n_gap_samples": d.n_gap_samples} for d in source.active]}
        if "playback" in state:
            pb = state["playback"]
            cards["output"] = {"card": pb.info.name, "latency_s": pb.latency_s, **pb.counters()}
        cards["batch_s"], cards["n_handouts"] = source.batch_s, source.n_handouts
        if record is not None:
            cards["recorded_to"] = str(record)
        if "status" in state:
            cards["last_status"] = state["status"].last
        report["cards"] = cards

    def on_end() -> None:
        if "playback" in state:
            state["playback"].ring.draining = True   # the stream is over: running dry is not an underflow

    # the audio callbacks need the GIL: hand it over every 1 ms (Python's default is 5 ms) so that a burst of
    # work in the stream loop (the first alignment releases seconds of audio at once) cannot starve them
    switch = sys.getswitchinterval()
    sys.setswitchinterval(min(switch, 0.001))
    try:
        return run_stream(source, out_dir, config=cfg, on_frame=on_frame,
                          extra_sinks=[Playback()] if output is not None else [],
                          status=status_cb if status else None, extra_report=extra, speech=speech, on_end=on_end)
    finally:
        sys.setswitchinterval(switch)
