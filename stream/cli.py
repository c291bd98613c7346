"""Command line: ``adhoc-array replay``, ``live``, ``devices`` and ``calibrate``.

Every option of :class:`stream.config.EngineConfig` is a flag of the same name, and can also be
given in a TOML file (``--config``). Errors the user can fix are printed as one sentence, exit 2.
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Any, Sequence

from .config import EngineConfig, load_toml
from .errors import AdhocArrayError, ConfigError, why_unreadable


def _add_engine_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("engine options (also accepted in a --config TOML file, same names)")
    g.add_argument("--estimator", choices=["tracks", "subset", "pinv", "kalman", "smoother"],
                   help="relative-TOA estimator (default: tracks = several sources with speech presence, steered at "
                        "the talker, never at a noise source; kalman = the TOA paper's single track, which follows "
                        "whatever is loudest, a third of the CPU)")
    g.add_argument("--target", help="whom to steer at with --estimator tracks: 'active-talker' (default) or "
                                    "'nearest DEVICE' (the talker closest to a device, by name or index)")
    g.add_argument("--tracker-lookahead-s", type=float,
                   help="--estimator tracks: steer each frame by the tracker's decision this many seconds later "
                        "(adds as much latency; default 0.128 for replay, 0 for live and network sources)")
    g.add_argument("--track-interval-s", type=float,
                   help="--estimator tracks: measure (GCC peaks, track update) every this many seconds at most, "
                        "in whole hops (default 0.016: every other hop at 16 kHz with a 128-sample hop; 0: every hop)")
    g.add_argument("--vad", help="speech-presence detector: auto (default: Silero, else WebRTC, else energy), "
                   "silero, webrtc or energy")
    g.add_argument("--gcc-weighting", choices=["subtract", "subtract-snr", "phat"],
                   help="noise cross-power removal before the PHAT weighting (default: subtract)")
    g.add_argument("--gcc-phat-beta", type=float,
                   help="the weighting's exponent: G / |G|^beta, in (0, 1] (default 1: plain PHAT; 0.9 gained on "
                        "simulated rooms and lost on measured ones: docs/tracking-log.md)")
    g.add_argument("--gcc-phat-beta-near-noise", action="store_const", const=True,
                   help="with --gcc-phat-beta below 1: that exponent only on the pairs near the noise, PHAT on "
                        "those that stand 30 dB clear of it")
    g.add_argument("--no-noise-drift", dest="noise_follows_drift", action="store_const", const=False,
                   help="keep the noise cross-power spectra where they were averaged (by default they follow the "
                        "clocks' drift, measured from the cross-power spectra: report.json's spectra_drift_ppm)")
    g.add_argument("--n-peaks", type=int, help="GCC-PHAT peaks kept per pair for the tracker (default 5)")
    g.add_argument("--gcc-smoothing-s", type=float,
                   help="short-time average of the cross-power spectra before the noise removal, seconds "
                        "(default 0.1; 0: every frame alone)")
    g.add_argument("--gcc-fast-smoothing-s", type=float,
                   help="the same average where a pair's frame stands 15-30 dB above the noise cross power, "
                        "seconds (default 0.03: a moving talker clear of the noise is followed closely)")
    g.add_argument("--noise-delay-s", type=float,
                   help="a frame joins the noise cross-power average this late, and only if no speech was heard "
                        "since (default 0.25: a talker's first words, before the detector fires, stay out of it)")
    g.add_argument("--working-rate-hz", type=float, help="rate every device is resampled to (default: first device's)")
    g.add_argument("--frame-samples", type=int, help="analysis frame (default: ~85 ms, 4096 at 48 kHz)")
    g.add_argument("--hop-samples", type=int, help="hop (default: frame/4, 75%% overlap); e.g. 512/128 for low latency")
    g.add_argument("--max-tdoa-s", type=float, help="largest fine TDOA searched by GCC-PHAT, in seconds")
    g.add_argument("--weighting", choices=["equal", "adaptive", "level"],
                   help="delay-and-sum channel weights (default level: equal weights on the devices brought to "
                        "one noise floor, learnt in the speech detector's pauses; equal without a detector)")
    g.add_argument("--level-snr-exponent", type=float,
                   help="--weighting level: each weight also times (the device's SNR over the median's)^(this / 2), "
                        "in [0, 2] (default 1: maximal-ratio combining; 0: the noise floors alone)")
    g.add_argument("--level-height-exponent", type=float,
                   help="--weighting level with the tracker: each weight also times (the device's mean matched GCC "
                        "peak height on the steered talker track over the median device's)^this, in [0, 4] "
                        "(default 1; 0: off)")
    g.add_argument("--accel-std-s-per-s2", type=float, help="Kalman process noise: TOA acceleration std")
    g.add_argument("--tdoa-std-s", type=float, help="Kalman measurement noise: TDOA std in seconds")
    g.add_argument("--gate-probability", type=float, help="Kalman clutter gate (chi-square probability)")
    g.add_argument("--min-confidence", type=float, help="smallest GCC-PHAT peak used (default 5/sqrt(frame))")
    g.add_argument("--init-max-residual-s", type=float,
                   help="Kalman starts only from a frame whose pseudo-inverse TDOA residual is below this")
    g.add_argument("--smoother-lag-frames", type=int, help="fixed-lag smoother delay in frames")
    g.add_argument("--align-window-s", type=float, help="audio used for the coarse start alignment")
    g.add_argument("--max-offset-s", type=float, help="largest start offset between devices searched")
    g.add_argument("--align-recheck-s", type=float, help="re-check the coarse alignment every this many seconds")
    g.add_argument("--device-deadline-s", type=float,
                   help="a device this far behind the others is left out until it catches up (default 2 s)")
    g.add_argument("--arrays", metavar="TOML", help="devices that are synchronous mic arrays: a TOML file with an "
                   "[[array]] table (name = the device's name, mics_m = its mics in metres) per array; each mic "
                   "is then a channel of its own (default: a device's channels are mixed down)")
    g.add_argument("--speed", type=float, help="pace the replay: 1.0 = real time (default: as fast as possible)")
    g.add_argument("--block-s", type=float, help="replay block length in seconds")
    g.add_argument("--no-plots", dest="plots", action="store_const", const=False, help="skip the PNG plots")
    g.add_argument("--no-progress", dest="progress", action="store_const", const=False, help="no progress bar")
    c = p.add_argument_group("calibration from a moving chirp beacon (on with --calibration-odometry)")
    c.add_argument("--calibration-odometry", metavar="CSV",
                   help="the beacon's odometry: dx_m,dy_m,dz_m[,interval_s], one row per step between chirps")
    c.add_argument("--chirp-interval-s", type=float, help="time between chirps, if the odometry has no interval_s")
    c.add_argument("--recalibrate-every", type=int, metavar="N", help="re-solve every N new chirps (default 8)")
    c.add_argument("--chirp-duration-s", type=float, help="the beacon's linear chirp: duration (default 0.1 s)")
    c.add_argument("--chirp-f0-hz", type=float, help="chirp start frequency (default 500 Hz)")
    c.add_argument("--chirp-f1-hz", type=float, help="chirp end frequency (default 6000 Hz)")
    c.add_argument("--chirp-threshold", type=float, help="detection threshold in robust noise units (default 10)")
    c.add_argument("--calibration-method", choices=["hybrid", "baseline"], help="solver (default hybrid)")
    c.add_argument("--calibration-apply", choices=["drift", "offsets", "none"],
                   help="what a new geometry corrects in the stream (default drift: resampling + offsets)")
    c.add_argument("--calibration-sigma-tdoa-s", type=float, help="assumed chirp TDOA noise (default 5e-5 s)")
    c.add_argument("--calibration-sigma-odo-m", type=float, help="assumed odometry noise per step and axis (0.01 m)")
    c.add_argument("--calibration-max-drift-std-ppm", type=float,
                   help="correct a device's drift once its CRLB std is at most this (default 5 ppm)")
    c.add_argument("--calibration-max-events", type=int, help="solve over at most the last this many chirps")
    c.add_argument("--calibration-executor", choices=["thread", "process"], help="where solves run (default thread)")
    c.add_argument("--calibration-replay-latency-s", type=float,
                   help="unpaced replay: adopt each solve this many stream seconds after it started, waiting for "
                        "it if needed, so the replay is reproducible on any machine (default 1.0; paced and live "
                        "streams never wait)")


def _add_net_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("network (Zenoh)")
    g.add_argument("--array", default="default", help="the array's name: its keys are adhoc/ARRAY/... (default "
                                                       "'default')")
    g.add_argument("--mode", choices=["peer", "client"], default="peer",
                   help="peer (default: peers on a LAN find each other by multicast scouting) or client (through "
                        "a router: --connect)")
    g.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="endpoint to connect to, e.g. tcp/192.168.1.10:7447 (repeatable)")
    g.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help="endpoint to listen on, e.g. tcp/0.0.0.0:7448 (repeatable)")
    g.add_argument("--zenoh-config", metavar="FILE",
                   help="a Zenoh JSON5 configuration, passed to Zenoh unchanged (TLS, user/password, access "
                        "control); --mode/--connect/--listen apply on top")
    g.add_argument("--no-scouting", dest="scouting", action="store_false",
                   help="no multicast scouting (give --connect/--listen)")


def _net(args: argparse.Namespace, mode: str | None = None):
    from .net import NetOptions
    return NetOptions(mode=mode or args.mode, connect=args.__dict__.get("connect") or (), listen=args.listen,
                      config_file=args.zenoh_config, scouting=args.scouting)


def _run_net(args: argparse.Namespace) -> int:
    from . import net
    net.quiet_zenoh()
    if args.command == "router":
        def ready(locators) -> None:
            print(f"adhoc-array router: listening on {', '.join(locators) or ', '.join(args.listen)}", flush=True)
        options = _net(args, "router")
        if not args.listen and not args.zenoh_config:
            options.listen = ["tcp/0.0.0.0:7447"]
        net.run_router(options, ready=ready)
        return 0
    if args.command == "listen":
        key = args.key if args.key.count("/") >= 2 else (
            net.Keys(args.array).audio(args.key[4:]) if args.key.startswith("dev/") else net.Keys(args.array).out(args.key))
        done = net.listen(key, args.out, _net(args), max_duration_s=args.duration, wait_s=args.wait_s)
        print(f"adhoc-array listen {key}: {done['n_frames']} frames, {done['n_samples']} samples, {done['n_gaps']} "
              f"gaps, {done['n_lines']} lines, {done['n_malformed']} malformed  ->  {args.out}")
        return 0
    if args.command == "device":
        source = _device_source(args)
        counters = net.run_device(args.name, source, _net(args), array=args.array, sample_format=args.sample_format,
                                  gain=args.gain, describe=args.input, wait_aggregator_s=args.wait_aggregator)
        print(f"adhoc-array device {args.name}: sent {counters.n_frames} frames ({counters.n_samples} samples, "
              f"{counters.n_bytes / 1e6:.2f} MB), {counters.n_put_errors} send errors")
        return 0
    layers = [(load_toml(args.config), args.config)] if args.config else []
    layers.append((_overrides(args), "command line"))
    expect = [n.strip() for n in args.expect.split(",") if n.strip()] if args.expect else []
    outcome = net.run_aggregate(args.out, _net(args), array=args.array, expect=expect, discover_s=args.discover_s,
                                jitter_s=args.jitter_s, until_done=args.until_done, max_duration_s=args.duration,
                                overrides=layers, status=args.status, spare=args.spare)
    print(summary(outcome.report, Path(args.out)))
    return 0 if outcome.report["status"] == "ok" else 1


def _device_source(args: argparse.Namespace):
    path = Path(args.input)
    if not path.exists() and ("/" in args.input or path.suffix.lower() in (".wav", ".flac", ".ogg", ".mp3", ".aiff")):
        raise ConfigError(f"--input {path} does not exist.")
    if path.is_file():
        import soundfile as sf
        from .replay import ReplaySource
        try:
            rate = sf.info(str(path)).samplerate
        except Exception as err:  # noqa: BLE001 - soundfile's errors: one sentence
            raise ConfigError(f"--input {path} is not a readable audio file ({why_unreadable(path, err)}).") from None
        if not args.speed > 0:
            raise ConfigError(f"--speed {args.speed} must be > 0")
        return ReplaySource([path], block_s=args.frame_samples / rate, speed=args.speed, names=[args.name],
                            start_s=args.start_s)
    from .cards import CardSource
    return CardSource([args.input], sample_rate_hz=args.card_rate_hz, block_samples=args.frame_samples,
                      names=[args.name])


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="adhoc-array", description="Streaming engine for ad-hoc microphone arrays.")
    parser.add_argument("-v", "--verbose", action="store_true", help="log more")
    sub = parser.add_subparsers(dest="command", required=True)
    rp = sub.add_parser("replay", help="replay recordings (one file per device, or a fixture folder) as live input",
                        description="Replay per-device recordings through the live path: resample, align, "
                                    "GCC-PHAT, TOA, delay-and-sum. Writes enhanced.wav, toa.csv, report.json, PNGs.")
    rp.add_argument("inputs", nargs="+", help="a fixture folder, or audio files (the first is the reference)")
    rp.add_argument("--out", required=True, help="output folder")
    rp.add_argument("--config", help="TOML file with engine options")
    _add_engine_options(rp)
    lp = sub.add_parser("live", help="sound cards in (one device per --input), enhanced audio out, until Ctrl-C",
                        description="Stream from sound cards, each with its own clock, through the same path as "
                                    "replay; play the enhanced stream on --output and write the outputs of replay "
                                    "into --out. Ctrl-C or SIGTERM ends the stream and writes every file.",
                        epilog="Cards are named by (part of) their name or by index (see: adhoc-array devices); "
                               "NAME:1,2 takes channels 1 and 2 of a card as one device with two microphones. "
                               "A card named by several --input is opened once.")
    lp.add_argument("--input", action="append", required=True, metavar="CARD[:CH,...]",
                    help="a sound card (one device of the array); repeat for each device, reference first")
    lp.add_argument("--output", metavar="CARD", help="card that plays the enhanced stream ('default' for the "
                                                      "system's default output)")
    lp.add_argument("--out", required=True, help="output folder (enhanced.wav, toa.csv, report.json, plots)")
    lp.add_argument("--record", metavar="DIR", help="also write every raw input into DIR (replayable: "
                                                     "adhoc-array replay DIR)")
    lp.add_argument("--rate", type=float, dest="card_rate_hz", metavar="HZ", help="open every card at this rate (default: each "
                                                                     "card's default rate)")
    lp.add_argument("--blocksize", type=int, default=0, help="PortAudio block size in samples (default: the host's)")
    lp.add_argument("--output-margin-s", type=float, default=0.01,
                    help="audio queued before the output card plays: a margin against hiccups, paid in latency, "
                         "rounded down to whole periods of the card (default 0.01; 0: lowest latency)")
    lp.add_argument("--batch-s", type=float, default=0.0, metavar="S",
                    help="process the input in batches of this much audio: fewer wake-ups of the stream, less CPU "
                         "(a quarter less at 0.032 with 8 devices at 16 kHz, hop 128), about that much more latency "
                         "(+22 ms at 0.032; default 0: every card period)")
    lp.add_argument("--duration", type=float, metavar="S", help="stop after this many seconds of audio from the reference card (default: Ctrl-C)")
    lp.add_argument("--no-status", dest="status", action="store_false", help="no live status line")
    lp.add_argument("--config", help="TOML file with engine options")
    _add_engine_options(lp)
    dp = sub.add_parser("device", help="stream one device (a sound card, or a file at real time) to the array",
                        description="A device agent: streams one microphone (or one recording, paced at real "
                                    "time) to the array's aggregator over Zenoh, until its input ends or Ctrl-C.",
                        epilog="The frames go to adhoc/ARRAY/dev/NAME/audio; the device's facts answer queries on "
                               "adhoc/ARRAY/dev/NAME/info; its liveliness token is adhoc/ARRAY/alive/NAME.")
    dp.add_argument("--name", required=True, help="the device's name in the array (unique)")
    dp.add_argument("--input", required=True, metavar="CARD[:CH,..]|FILE",
                    help="a sound card (as live --input) or an audio file replayed as a live device")
    dp.add_argument("--speed", type=float, default=1.0, help="a file's pace: 1.0 real time (default), 2.0 twice")
    dp.add_argument("--start-s", type=float, default=0.0, help="a file: start this far into it (default 0)")
    dp.add_argument("--frame-samples", type=int, default=1024, help="samples per frame (default 1024)")
    dp.add_argument("--format", dest="sample_format", choices=["int16", "float32"], default="int16",
                    help="sample format on the wire (default int16)")
    dp.add_argument("--gain", type=float, default=1.0, help="multiply the samples (default 1)")
    dp.add_argument("--wait-aggregator", type=float, default=0.0, metavar="S",
                    help="start only once an aggregator is there (waiting up to S seconds): a file then loses "
                         "nothing (default 0: start at once)")
    dp.add_argument("--rate", type=float, dest="card_rate_hz", metavar="HZ", help="open the card at this rate")
    _add_net_options(dp)
    ap = sub.add_parser("aggregate", help="run the engine on every device of the array, over Zenoh",
                        description="Discover the array's devices (liveliness), run the engine on their frames and "
                                    "write what replay writes into --out; publish the enhanced audio, the TOA "
                                    "estimates and the geometry on adhoc/ARRAY/out/{enhanced,toa,geometry}.")
    ap.add_argument("--out", required=True, help="output folder")
    ap.add_argument("--expect", help="device names of the array, reference first (comma-separated); the stream "
                                     "starts once all are present (or after --discover-s); absent ones are "
                                     "concealed until they join")
    ap.add_argument("--spare", type=int, default=0, metavar="N",
                    help="keep N free slots for devices that join after the stream started and are not in --expect "
                         "(each costs like a device; default 0: such a device is left out, with one sentence)")
    ap.add_argument("--discover-s", type=float, default=5.0, help="longest wait for devices (default 5 s)")
    ap.add_argument("--jitter-s", type=float, default=0.1,
                    help="how long a missing frame is waited for before it is concealed (default 0.1 s)")
    ap.add_argument("--until-done", action="store_true",
                    help="end when every device has ended its stream (default: only Ctrl-C ends)")
    ap.add_argument("--duration", type=float, metavar="S", help="stop after this much audio of the reference")
    ap.add_argument("--no-status", dest="status", action="store_false", help="no status line")
    ap.add_argument("--config", help="TOML file with engine options")
    _add_net_options(ap)
    _add_engine_options(ap)
    rt = sub.add_parser("router", help="a Zenoh router, for networks without multicast or many devices",
                        description="Runs a Zenoh router (zenoh-python's router mode) until Ctrl-C; devices and "
                                    "the aggregator reach it with --mode client --connect ENDPOINT.")
    rt.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                    help="endpoint to listen on (default tcp/0.0.0.0:7447); repeatable")
    rt.add_argument("--zenoh-config", metavar="FILE", help="a Zenoh JSON5 configuration (TLS, access control)")
    rt.add_argument("--no-scouting", dest="scouting", action="store_false", help="no multicast scouting")
    ls = sub.add_parser("listen", help="record what the array publishes (enhanced audio, TOA, a device's frames)",
                        description="Subscribe to KEY and record it: audio frames into a WAV (gaps as zeros), "
                                    "anything else as one line each.")
    ls.add_argument("key", help="enhanced, toa or geometry (this array's outputs), dev/NAME (a device's audio), "
                                "or a full key expression")
    ls.add_argument("--out", required=True, help="file to write (.wav for audio, text otherwise)")
    ls.add_argument("--duration", type=float, metavar="S", help="stop after this much audio")
    ls.add_argument("--wait-s", type=float, help="stop after this long with nothing received")
    _add_net_options(ls)
    sub.add_parser("devices", help="list the sound cards (channels, rates)",
                   description="List every sound card PortAudio sees, with its channels and default rate; "
                               "use a part of the name (or the index) with live --input/--output.")
    cp = sub.add_parser(
        "calibrate", help="batch calibration: positions, clock offsets and drifts of the devices",
        description="Solve the array geometry from measured TDOAs (--measurements FILE) or from one recording "
                    "per device with the beacon's chirps plus its odometry (AUDIO... --odometry FILE). Writes "
                    "geometry.json (positions, offsets, drifts with their CRLB standard deviations, verdict), "
                    "geometry.png and calibration.json.",
        epilog="Measurement files: .npz or .json with tdoa_events_s (K-1, N), tdoa_mics_s (K, N), odometry_m "
               "(K-1, 3), interval_s (K-1,), sigma_tdoa_s, sigma_odo_m (optional: sigma_tdoa_mics_s, "
               "speed_of_sound_m_s, truth_positions_m, device_names); or a recNN.npz of the hybrid-TDOA real data "
               "(tdoa_s, tdoa_m_arr2/3, S, dt; choose its mics with --mics).")
    cp.add_argument("audio", nargs="*", help="one recording per device (device 0 first), with --odometry")
    src = cp.add_mutually_exclusive_group()
    src.add_argument("--measurements", metavar="FILE", help="measured TDOAs and odometry (.npz or .json)")
    src.add_argument("--odometry", metavar="CSV", help="the beacon's odometry for AUDIO (dx_m,dy_m,dz_m[,interval_s])")
    cp.add_argument("--out", required=True, help="output folder")
    cp.add_argument("--method", choices=["hybrid", "baseline", "multi-array"], default="hybrid",
                    help="solver (default hybrid); multi-array: poses of synchronous arrays from probe recordings "
                         "(--arrays)")
    cp.add_argument("--arrays", metavar="TOML|DIR", help="multi-array: the arrays file (name, file, mics_m per "
                                                          "array), or a folder holding arrays.toml")
    cp.add_argument("--multi-array-method", choices=["mle", "rigid_body"], default="mle",
                    help="multi-array: maximum likelihood (default) or the rigid-body baseline")
    cp.add_argument("--mics", help="hybrid-TDOA real data: global mic numbers, e.g. 0,6,12,9,13,15 (array 1 first)")
    cp.add_argument("--chirp-interval-s", type=float, help="time between chirps, if the odometry has no interval_s")
    cp.add_argument("--chirp-duration-s", type=float, default=0.1, help="chirp duration (default 0.1 s)")
    cp.add_argument("--chirp-f0-hz", type=float, default=500.0, help="chirp start frequency (default 500 Hz)")
    cp.add_argument("--chirp-f1-hz", type=float, default=6000.0, help="chirp end frequency (default 6000 Hz)")
    cp.add_argument("--sigma-tdoa-s", type=float, help="TDOA noise (default: the file's, or 5e-5 s for audio)")
    cp.add_argument("--sigma-odo-m", type=float, help="odometry noise (default: the file's, or 0.01 m)")
    cp.add_argument("--seed", type=int, default=0, help="solver restarts' random seed")
    cp.add_argument("--no-plots", dest="plots", action="store_false", help="skip geometry.png")
    return parser


def _overrides(args: argparse.Namespace) -> dict[str, Any]:
    names = EngineConfig.__dataclass_fields__.keys()
    return {k: v for k, v in vars(args).items() if k in names and v is not None}


def _fmt(v: Any, spec: str = ".2f") -> str:
    return "n/a" if v is None or v != v else format(v, spec)


def summary(report: dict[str, Any], out: Path) -> str:
    """One screen: what ran, on what, how fast, how well, and what went wrong."""
    lines = []
    st = report.get("stream", {})
    tm = report.get("timing", {})
    kind = "aggregate" if "network" in report else "live" if report.get("live") else "replay"
    lines.append(f"adhoc-array {kind}: {report.get('status')}  ->  {out}"
                 + (f"  (stopped by {report['stopped_by']})" if report.get("stopped_by") else ""))
    if st:
        n_arrays = len(report.get("arrays", {}))
        arrays = (f" ({n_arrays} arra{'ys' if n_arrays > 1 else 'y'}: {st['n_channels']} channels)"
                  if n_arrays else "")
        lines.append(f"  {st['n_devices']} devices{arrays} at {st['working_rate_hz']:g} Hz, frame {st['frame_samples']} / hop "
                     f"{st['hop_samples']}, {st['audio_s']:.1f} s of audio, output latency "
                     f"{1e3 * st['output_latency_s']:.1f} ms"
                     + (f" (the tracker's look-ahead {1e3 * st['tracker_lookahead_s']:.0f} ms included)"
                        if st.get("tracker_lookahead_s") else ""))
        every = st.get("tracker_every_hops", 1)
        lines.append(f"  estimator {report['settings']['estimator']}"
                     + (f" (measuring every {every} hops, {1e3 * every * st['hop_samples'] / st['working_rate_hz']:.0f} ms)"
                        if every > 1 else "")
                     + f": {st['n_gated']} of {st['n_blocks']} frames gated"
                     f", {st['n_recentred']} re-centrings, coarse offsets (s) "
                     + " ".join(f"{o:+.3f}" for o in st["coarse_offsets_s"]))
    if tm:
        lines.append(f"  speed: {tm['wall_s']:.2f} s wall ({_fmt(tm.get('real_time_factor'), '.3f')} x real time), "
                     f"per hop median {tm['block_ms_median']:.2f} ms"
                     + (f" (mean {tm['block_ms_mean']:.2f})" if "block_ms_mean" in tm else "") + f" of {tm['hop_ms']:.1f} ms")
    m = report.get("metrics", {})
    if "toa" in m:
        lines.append("  TOA RMSE (eq. 18, samples): " + ", ".join(
            f"{k} {_fmt(v['rmse_samples'], '.1f')}" for k, v in m["toa"].items()))
    enh = m.get("enhancement", {})
    if enh:
        def row(name, key):
            v = enh.get(key)
            if v:
                ssara = _fmt(v.get("ssara_db"), "6.2f")
                lines.append(f"  {name:<36} SI-SDR {_fmt(v['si_sdr_db'], '6.2f')} dB  STOI {_fmt(v['stoi'], '.3f')}"
                             + (f"  SSARA {ssara} dB" if ssara != "n/a" else ""))
        weighting = report["settings"]["weighting"]
        row(f"enhanced ({weighting} weights)", "engine")
        other = "adaptive" if weighting == "equal" else "equal"
        row(f"estimated TOA, {other} weights", f"estimated_toa_{other}_weights")
        # the true-TOA baselines are scored with equal and adaptive weights ("level" learns from a detector's pauses)
        scored, note = (weighting, "") if weighting != "level" else ("equal", ", equal")
        row(f"true TOA, async input{note}", f"true_toa_async_{scored}")
        row(f"true TOA, synchronous signals{note}", f"true_toa_sync_{scored}")
        b = enh.get("best_single_device")
        if b:
            row(f"best single device ({b['device']})", "best_single_device")
    cal = report.get("calibration")
    if cal:
        g = cal.get("geometry")
        lines.append(f"  calibration ({cal['method']}, apply {cal['apply']}): {cal['n_solves']} solves, "
                     f"{cal['n_adopted']} adopted, chirps heard " + "/".join(str(n) for n in cal["n_detections"])
                     + (f"; last geometry over {g['n_events']} events" if g else "; no good geometry"))
        for m in cal.get("messages", [])[:4]:
            lines.append(f"  ! {m}")
    cards = report.get("cards")
    if cards:
        lines.append("  cards: " + ", ".join(f"{c['name']} ({c['card']} ch {','.join(map(str, c['channels']))}, "
                                            f"{c['sample_rate_hz']:g} Hz, {c['n_overflows']} overflows"
                                            + (f" ({c['overflows_s'][0]:.1f}-{c['overflows_s'][1]:.1f} s)"
                                               if c.get("overflows_s") else "")
                                            + f", {c['n_gaps']} gaps)" for c in cards["inputs"]))
        if "output" in cards:
            o = cards["output"]
            skipped = o["n_dropped_samples"] / st["working_rate_hz"] if st else 0.0
            when = (f" ({o['underflows_s'][0]:.1f}-{o['underflows_s'][1]:.1f} s)" if o.get("underflows_s") else "")
            lines.append(f"  output {o['card']}: {o['n_underflows']} underflows{when}; {skipped:.1f} s of output skipped to "
                         "stay live (the start-up alignment releases its audio at once)")
        if "recorded_to" in cards:
            lines.append(f"  raw inputs recorded to {cards['recorded_to']} (adhoc-array replay {cards['recorded_to']})")
    nw = report.get("network")
    if nw:
        for name, d in nw["devices"].items():
            lat = d.get("latency_ms", {})
            lines.append(f"  {name}: {d['n_frames']} frames, {d['n_lost_frames']} lost, {d['n_reordered']} reordered, "
                         f"{d['n_concealed_samples']} samples concealed, {d['n_restarts']} restarts; capture to "
                         f"arrival p50 {_fmt(lat.get('p50'), '.1f')} / p99 {_fmt(lat.get('p99'), '.1f')} ms")
        for key, n in nw.get("malformed", {}).items():
            lines.append(f"  ! {n} malformed frames from {key} were rejected")
    problems = [p for d in report.get("devices", []) for p in d.get("problems", [])]
    for p in problems[:8]:
        lines.append(f"  ! {p}")
    if len(problems) > 8:
        lines.append(f"  ! ... {len(problems) - 8} more in report.json")
    if report.get("error"):
        lines.append(f"  ! {report['error']}")
    lines.append(f"  wrote: {', '.join(report.get('outputs', []))}")
    return "\n".join(lines)


def calibration_summary(result: dict[str, Any], out: Path) -> str:
    """One screen for ``adhoc-array calibrate``."""
    g = result["geometry"]
    lines = [f"adhoc-array calibrate: {g.verdict}  ->  {out}",
             f"  {g.method}: {g.n_devices} devices, {g.n_events} events, solved in {1e3 * g.solve_time_s:.1f} ms"]
    names = list(g.device_names) or [f"dev{i}" for i in range(g.n_devices)]
    for i in range(g.n_devices):
        p = g.positions_m[i]
        lines.append(f"  {names[i]:>8}: ({p[0]:+.3f}, {p[1]:+.3f}, {p[2]:+.3f}) m ± {_fmt(g.position_std_m[i], '.3f')}"
                     f"   offset {_fmt(1e3 * g.offsets_s[i], '+.3f')} ± {_fmt(1e3 * g.offset_std_s[i], '.3f')} ms"
                     f"   drift {_fmt(g.drifts_ppm[i], '+.1f')} ± {_fmt(g.drift_std_ppm[i], '.1f')} ppm")
    if "location_error_m" in result:
        lines.append(f"  against the file's ground truth (mic frame): location RMS "
                     f"{result['location_error_m']['rms']:.3f} m")
    for reason in g.rejected[:6]:
        lines.append(f"  rejected: {reason}")
    if len(g.rejected) > 6:
        lines.append(f"  rejected: ... {len(g.rejected) - 6} more in geometry.json")
    if not g.converged:
        lines.append(f"  ! the solver's verdict is '{g.verdict}': do not use this geometry")
    lines.append(f"  wrote: {', '.join(result['outputs'])}")
    return "\n".join(lines)


def multi_array_summary(result: dict[str, Any], out: Path) -> str:
    """One screen for ``adhoc-array calibrate --method multi-array``."""
    verdict = "converged" if result["converged"] else "NOT converged: do not use these poses"
    lines = [f"adhoc-array calibrate (multi-array, {result['method']}): {verdict}  ->  {out}",
             f"  {len(result['arrays'])} arrays, {result['n_probes']} probes heard by all, "
             f"{len(result['rejected_probes'])} rejected as outliers, {1e3 * result['solve_s']:.0f} ms"]
    for a in result["arrays"]:
        r, rs = a["rotation_deg"], a["rotation_std_deg"]
        t, ts = a["translation_m"], a["translation_std_m"]
        lines.append(f"  {a['name']:>10}: roll/pitch/yaw ({r[0]:+.1f}, {r[1]:+.1f}, {r[2]:+.1f})° "
                     f"± ({rs[0]:.1f}, {rs[1]:.1f}, {rs[2]:.1f})   t ({t[0]:+.3f}, {t[1]:+.3f}, {t[2]:+.3f}) m "
                     f"± ({ts[0]:.3f}, {ts[1]:.3f}, {ts[2]:.3f})   {a['n_events']} events")
    if result["rejected_probes"]:
        lines.append(f"  rejected probes (inconsistent across the arrays): {result['rejected_probes']}")
    lines.append(f"  wrote: {', '.join(result['outputs'])}")
    return "\n".join(lines)


def _run_calibrate(args: argparse.Namespace) -> int:
    if args.method == "multi-array":
        from .arrays import run_multi_array
        if not args.arrays:
            raise ConfigError("--method multi-array needs --arrays FILE (name, file and mics_m of each array).")
        result = run_multi_array(args.arrays, args.out, method=args.multi_array_method, sigma_tdoa_s=args.sigma_tdoa_s,
                                 seed=args.seed, plots=args.plots)
        print(multi_array_summary(result, Path(args.out)))
        return 0 if result["converged"] else 1
    from .calibrate_cli import run_calibrate
    mics = None
    if args.mics:
        try:
            mics = [int(v) for v in args.mics.split(",")]
        except ValueError:
            raise ConfigError(f"--mics {args.mics!r} must be comma-separated integers") from None
    if args.measurements is None and args.odometry is None:
        raise ConfigError("Give --measurements FILE, or one audio file per device and --odometry FILE.")
    if args.measurements is not None and args.audio:
        raise ConfigError("Give either --measurements FILE or audio files with --odometry, not both.")
    result = run_calibrate(args.out, measurements=args.measurements, audio=args.audio, odometry=args.odometry,
                           method=args.method, mics=mics, chirp_interval_s=args.chirp_interval_s,
                           chirp_duration_s=args.chirp_duration_s, chirp_f0_hz=args.chirp_f0_hz,
                           chirp_f1_hz=args.chirp_f1_hz, sigma_tdoa_s=args.sigma_tdoa_s,
                           sigma_odo_m=args.sigma_odo_m, seed=args.seed, plots=args.plots)
    print(calibration_summary(result, Path(args.out)))
    return 0 if result["geometry"].converged else 1


def _run_live(args: argparse.Namespace) -> int:
    from .live import run_live
    try:
        layers = [(load_toml(args.config), args.config)] if args.config else []
        layers.append((_overrides(args), "command line"))
        if args.duration is not None and not args.duration > 0:
            raise ConfigError(f"--duration {args.duration} must be > 0 seconds")
        if not 0 <= args.batch_s <= 1.0:
            raise ConfigError(f"--batch-s {args.batch_s} must be in 0..1 seconds")
        outcome = run_live(args.input, args.out, output=args.output, record=args.record,
                           sample_rate_hz=args.card_rate_hz, block_samples=args.blocksize, overrides=layers,
                           status=args.status, max_duration_s=args.duration,
                           output_margin_s=args.output_margin_s, batch_s=args.batch_s)
    except AdhocArrayError as err:
        print(f"adhoc-array: {err}", file=sys.stderr)
        return 2
    print(summary(outcome.report, Path(args.out)))
    return 0 if outcome.report["status"] == "ok" else 1


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s: %(message)s")
    if args.command == "replay":
        from .run import run_replay
        try:
            layers = [(load_toml(args.config), args.config)] if args.config else []
            layers.append((_overrides(args), "command line"))
            outcome = run_replay(args.inputs, args.out, config=EngineConfig(), overrides=layers)
        except AdhocArrayError as err:
            print(f"adhoc-array: {err}", file=sys.stderr)
            return 2
        print(summary(outcome.report, Path(args.out)))
        return 0 if outcome.report["status"] == "ok" else 1
    if args.command == "devices":
        try:
            from .cards import list_cards
            cards = list_cards()
        except AdhocArrayError as err:
            print(f"adhoc-array: {err}", file=sys.stderr)
            return 2
        if not cards:
            print("adhoc-array: no sound card is visible to PortAudio (no device, or no audio server running).",
                  file=sys.stderr)
            return 1
        for c in cards:
            print(c.describe())
        return 0
    if args.command == "live":
        return _run_live(args)
    if args.command in ("device", "aggregate", "router", "listen"):
        try:
            return _run_net(args)
        except AdhocArrayError as err:
            print(f"adhoc-array: {err}", file=sys.stderr)
            return 2
    if args.command == "calibrate":
        try:
            return _run_calibrate(args)
        except AdhocArrayError as err:
            print(f"adhoc-array: {err}", file=sys.stderr)
            return 2
    parser.error(f"unknown command {args.command}")
    return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
