"""Build ``stream/models/silero_vad_8k.onnx``: the shipped two-rate Silero VAD (``silero_vad.onnx``) with its
rate fixed at 8 kHz and its window at the engine's 288 samples (256 new ones and 32 of context), so that
onnxruntime runs the convolutions and the LSTM only, not the export's control flow.

The two-rate export picks its 8 or 16 kHz branch with an ``If`` on the ``sr`` input, and the branch holds more
``If`` nodes on shapes (whether the encoder's output has one time step, whether a state was given). Here each
``If`` is replaced by the branch its condition takes: the rate's by the 8 kHz branch; the others by asking
onnxruntime for the conditions' values on a 288-sample window (the same for 1 and 8 devices, checked). Then
``onnxsim`` (a well-kept simplifier) folds the constants and the shape arithmetic: 187 nodes to 46. The output
and the state are the two-rate model's at 8 kHz to the bit (checked here on the fixtures' speech, and by
``tests/stream/test_sources.py`` on every run).

Run from the repository root (it needs ``onnx`` and ``onnxsim``, the ``tools`` extra, which the engine does not)::

    pip install -e ".[tools]" && python tools/silero_8k.py
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import onnxruntime as ort
import soundfile as sf

try:   # the build needs onnx and onnxsim (the ``tools`` extra); :func:`compare` (and the test) only onnxruntime
    import onnx
    import onnxsim
    from onnx import helper
except ImportError:
    onnx = onnxsim = helper = None

ROOT = Path(__file__).resolve().parents[1]
SOURCE = ROOT / "stream" / "models" / "silero_vad.onnx"
TARGET = ROOT / "stream" / "models" / "silero_vad_8k.onnx"
RATE_HZ, WINDOW = 8000, 288


def _inline(graph: onnx.GraphProto, node: onnx.NodeProto, branch: str) -> None:
    """Replace the ``If`` ``node`` by the nodes of its ``branch`` (they read the outer names directly)."""
    sub = next(a.g for a in node.attribute if a.name == branch)
    new = list(sub.node) + [helper.make_node("Identity", [o.name], [name]) for o, name in zip(sub.output, node.output)]
    graph.initializer.extend(sub.initializer)
    nodes = list(graph.node)
    i = nodes.index(node)
    nodes[i:i + 1] = new
    del graph.node[:]
    graph.node.extend(nodes)


def _session(model: onnx.ModelProto) -> ort.InferenceSession:
    opts = ort.SessionOptions()
    opts.log_severity_level = 3
    return ort.InferenceSession(model.SerializeToString(), sess_options=opts, providers=["CPUExecutionProvider"])


def _conditions(model: onnx.ModelProto, names: list[str], n_devices: int) -> dict[str, bool]:
    """The values of the boolean tensors ``names`` on a window of ``n_devices`` devices."""
    probe = onnx.ModelProto()
    probe.CopyFrom(model)
    for name in names:
        probe.graph.output.append(helper.make_tensor_value_info(name, onnx.TensorProto.BOOL, None))
    rng = np.random.default_rng(0)
    feed = {"input": (0.1 * rng.standard_normal((n_devices, WINDOW))).astype(np.float32),
            "state": np.zeros((2, n_devices, 128), np.float32), "sr": np.array(RATE_HZ, np.int64)}
    values = _session(probe).run(names, feed)
    return {n: bool(np.asarray(v).ravel()[0]) for n, v in zip(names, values)}


def fix_rate(model: onnx.ModelProto) -> onnx.ModelProto:
    graph = model.graph
    (top,) = [n for n in graph.node if n.op_type == "If"]   # sr == 16000: then; 8 kHz: else
    _inline(graph, top, "else_branch")
    while ifs := [n for n in graph.node if n.op_type == "If"]:
        names = [n.input[0] for n in ifs]
        one, eight = _conditions(model, names, 1), _conditions(model, names, 8)
        if one != eight:
            raise RuntimeError(f"the model's branches depend on the number of devices: {one} against {eight}")
        for n in ifs:
            _inline(graph, n, "then_branch" if eight[n.input[0]] else "else_branch")
    fixed = onnx.utils.Extractor(model).extract_model(["input", "state"], ["output", "stateN"])
    for inp in fixed.graph.input:   # any number of devices, the engine's window
        dims = inp.type.tensor_type.shape.dim
        if inp.name == "input":
            dims[0].dim_param, dims[1].dim_value = "devices", WINDOW
        else:
            dims[1].dim_param = "devices"
    simple, ok = onnxsim.simplify(fixed)
    if not ok:
        raise RuntimeError("onnxsim could not check the simplified model")
    return simple


def compare(two_rate, fixed, x: np.ndarray) -> np.ndarray:
    """Run both models (onnxruntime sessions) over ``x`` (n_devices, n_samples) at 8 kHz in 32 ms windows, all
    devices in one call, the state carried from window to window. Raises unless output and state are equal to
    the bit; returns the two-rate model's speech probabilities, shape (n_windows, n_devices)."""
    sa = sb = np.zeros((2, len(x), 128), np.float32)
    context = np.zeros((len(x), WINDOW - 256), np.float32)
    p = []
    for start in range(0, x.shape[1] - 256 + 1, 256):
        window = np.concatenate([context, x[:, start:start + 256]], axis=1)
        context = window[:, -(WINDOW - 256):]
        pa, sa = two_rate.run(None, {"input": window, "state": sa, "sr": np.array(RATE_HZ, np.int64)})
        pb, sb = fixed.run(None, {"input": window, "state": sb})
        if not (np.array_equal(pa, pb) and np.array_equal(sa, sb)):
            raise RuntimeError(f"window {len(p)}: the fixed-rate model differs from the two-rate one")
        p.append(pa[:, 0])
    return np.array(p)


def check_same(fixed: onnx.ModelProto) -> int:
    """:func:`compare` over the fixtures' devices; the number of windows compared."""
    import soxr
    x = []
    for name in ("meeting_table", "kitchen_noise"):
        for path in sorted((ROOT / "replay_fixtures" / name).glob("dev*.flac"))[:4]:
            y, fs = sf.read(path, dtype="float32", frames=int(6.0 * 48000))
            x.append(soxr.resample(y if y.ndim == 1 else y.mean(axis=1), fs, RATE_HZ)[:int(5.0 * RATE_HZ)])
    x = np.stack([np.pad(y, (0, int(5.0 * RATE_HZ) - len(y))) for y in x]).astype(np.float32)
    return len(compare(_session(onnx.load(str(SOURCE))), _session(fixed), x))


def main() -> int:
    if onnx is None:
        print("tools/silero_8k.py needs onnx and onnxsim: pip install -e \".[tools]\"", file=sys.stderr)
        return 1
    fixed = fix_rate(onnx.load(str(SOURCE)))
    n = check_same(fixed)
    onnx.save(fixed, str(TARGET))
    print(f"wrote {TARGET.relative_to(ROOT)} ({TARGET.stat().st_size} bytes, {len(fixed.graph.node)} nodes); "
          f"the same output and state to the bit as {SOURCE.name} over {n} windows of 8 devices")
    return 0


if __name__ == "__main__":
    sys.exit(main())
