"""Command line: ``adhoc-array replay``.

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
from .errors import AdhocArrayError


def _add_engine_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("engine options (also accepted in a --config TOML file, same names)")
    g.add_argument("--estimator", choices=["subset", "pinv", "kalman", "smoother"],
                   help="relative-TOA estimator (default: kalman)")
    g.add_argument("--working-rate-hz", type=float, help="rate every device is resampled to (default: first device's)")
    g.add_argument("--frame-samples", type=int, help="analysis frame (default: ~85 ms, 4096 at 48 kHz)")
    g.add_argument("--hop-samples", type=int, help="hop (default: frame/4, 75%% overlap); e.g. 512/128 for low latency")
    g.add_argument("--max-tdoa-s", type=float, help="largest fine TDOA searched by GCC-PHAT, in seconds")
    g.add_argument("--weighting", choices=["equal", "adaptive"], help="delay-and-sum channel weights")
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
    g.add_argument("--speed", type=float, help="pace the replay: 1.0 = real time (default: as fast as possible)")
    g.add_argument("--block-s", type=float, help="replay block length in seconds")
    g.add_argument("--no-plots", dest="plots", action="store_const", const=False, help="skip the PNG plots")
    g.add_argument("--no-progress", dest="progress", action="store_const", const=False, help="no progress bar")


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
    lines.append(f"adhoc-array replay: {report.get('status')}  ->  {out}")
    if st:
        lines.append(f"  {st['n_devices']} devices at {st['working_rate_hz']:g} Hz, frame {st['frame_samples']} / hop "
                     f"{st['hop_samples']}, {st['audio_s']:.1f} s of audio, output latency "
                     f"{1e3 * st['output_latency_s']:.1f} ms")
        lines.append(f"  estimator {report['settings']['estimator']}: {st['n_gated']} of {st['n_blocks']} frames gated"
                     f", {st['n_recentred']} re-centrings, coarse offsets (s) "
                     + " ".join(f"{o:+.3f}" for o in st["coarse_offsets_s"]))
    if tm:
        lines.append(f"  speed: {tm['wall_s']:.2f} s wall ({_fmt(tm.get('real_time_factor'), '.3f')} x real time), "
                     f"per hop median {tm['block_ms_median']:.2f} ms of {tm['hop_ms']:.1f} ms")
    m = report.get("metrics", {})
    if "toa" in m:
        lines.append("  TOA RMSE (eq. 18, samples): " + ", ".join(
            f"{k} {_fmt(v['rmse_samples'], '.1f')}" for k, v in m["toa"].items()))
    enh = m.get("enhancement", {})
    if enh:
        def row(name, key):
            v = enh.get(key)
            if v:
                lines.append(f"  {name:<34} SI-SDR {_fmt(v['si_sdr_db'], '6.2f')} dB  STOI {_fmt(v['stoi'], '.3f')}"
                             f"  SSARA {_fmt(v['ssara_db'], '6.2f')} dB")
        row("enhanced (this run)", "engine")
        row("estimated TOA, equal weights", "estimated_toa_equal_weights")
        row("true TOA, async input", f"true_toa_async_{report['settings']['weighting']}")
        row("true TOA, synchronous signals", f"true_toa_sync_{report['settings']['weighting']}")
        b = enh.get("best_single_device")
        if b:
            row(f"best single device ({b['device']})", "best_single_device")
    problems = [p for d in report.get("devices", []) for p in d.get("problems", [])]
    for p in problems[:8]:
        lines.append(f"  ! {p}")
    if len(problems) > 8:
        lines.append(f"  ! ... {len(problems) - 8} more in report.json")
    if report.get("error"):
        lines.append(f"  ! {report['error']}")
    lines.append(f"  wrote: {', '.join(report.get('outputs', []))}")
    return "\n".join(lines)


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
    parser.error(f"unknown command {args.command}")
    return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
