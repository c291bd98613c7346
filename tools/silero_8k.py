"""Build ``stream/models/silero_vad_8k.onnx``: the shipped two-rate Silero VAD (``silero_vad.onnx``) with its
rate fixed at 8 kHz and its window at the engine's 288 samples (256 new ones and 32 of context), so that
onnxruntime runs the convolutions and the LSTM only, not the export's control flow, each convolution as one
matrix product over every device.

The two-rate export picks its 8 or 16 kHz branch with an ``If`` on the ``sr`` input, and the branch holds more
``If`` nodes on shapes (whether the encoder's output has one time step, whether a state was given). Here each
``If`` is replaced by the branch its condition takes: the rate's by the 8 kHz branch; the others by asking
onnxruntime for the conditions' values on a 288-sample window (the same for 1 and 8 devices, checked). Then
``onnxsim`` (a well-kept simplifier) folds the constants and the shape arithmetic: 187 nodes to 46. That
model's output and state are the two-rate model's at 8 kHz to the bit.

Then :func:`as_matrix_products` writes the same network with each ``Conv`` as one ``Gemm``: at 288 samples the
STFT has 4 frames and the encoder 4, 2, 1 and 1, so a convolution is a matrix product of the frames' stacked
taps (every device and frame a row) with the reshaped kernel. onnxruntime runs a 1-D ``Conv`` as a small
product per device; the batched call for 8 devices takes about a third of the time (283 against 104 us, one
process, alternating; the LSTM is then a third of the call). The sums run in another order, so the output is
not the same to the bit: over the fixtures' 29 devices (12,035 windows) the speech probability differs by at
most 2.3e-6 and the state by 5.5e-5, and not one decision of the engine's hysteresis differs. The build checks
that (:func:`compare`) before it writes, and ``tests/stream/test_sources.py`` on every run.

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
    from onnx import helper, numpy_helper
except ImportError:
    onnx = onnxsim = helper = numpy_helper = None

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from stream.speech import SILERO_OFF, SILERO_ON  # noqa: E402  (the engine's hysteresis: the decisions compared)
SOURCE = ROOT / "stream" / "models" / "silero_vad.onnx"
TARGET = ROOT / "stream" / "models" / "silero_vad_8k.onnx"
RATE_HZ, WINDOW = 8000, 288
MAX_PROBABILITY_DIFF = 1e-5    # the matrix-product form against the two-rate model (module doc: 2.3e-6 measured)


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
    devices in one call, the state carried from window to window. Raises unless every speech probability is
    within ``MAX_PROBABILITY_DIFF`` and every decision of ``stream.speech``'s hysteresis is the
    same; returns the two-rate model's speech probabilities, shape (n_windows, n_devices)."""
    sa = sb = np.zeros((2, len(x), 128), np.float32)
    context = np.zeros((len(x), WINDOW - 256), np.float32)
    on_a = on_b = np.zeros(len(x), bool)
    p = []
    for start in range(0, x.shape[1] - 256 + 1, 256):
        window = np.concatenate([context, x[:, start:start + 256]], axis=1)
        context = window[:, -(WINDOW - 256):]
        pa, sa = two_rate.run(None, {"input": window, "state": sa, "sr": np.array(RATE_HZ, np.int64)})
        pb, sb = fixed.run(None, {"input": window, "state": sb})
        on_a = np.where(on_a, pa[:, 0] >= SILERO_OFF, pa[:, 0] >= SILERO_ON)
        on_b = np.where(on_b, pb[:, 0] >= SILERO_OFF, pb[:, 0] >= SILERO_ON)
        if np.abs(pa - pb).max() > MAX_PROBABILITY_DIFF or np.any(on_a != on_b):
            raise RuntimeError(f"window {len(p)}: the engine's model differs from the two-rate one "
                               f"(probabilities by {np.abs(pa - pb).max():.2g}, decisions {np.sum(on_a != on_b)})")
        p.append(pa[:, 0])
    return np.array(p)


def as_matrix_products(fixed: onnx.ModelProto) -> onnx.ModelProto:
    """The fixed-rate model ``fixed`` (:func:`fix_rate`) with every convolution a ``Gemm`` over all devices
    and frames (module doc). Inputs, outputs and weights are the same; the layers' shapes are those of a
    288-sample window."""
    weights = {i.name: numpy_helper.to_array(i) for i in fixed.graph.initializer}
    weights |= {n.output[0]: numpy_helper.to_array(n.attribute[0].t)
                for n in fixed.graph.node if n.op_type == "Constant"}

    def weight(suffix: str) -> np.ndarray:
        (name,) = [k for k in weights if k.endswith(suffix)]
        return weights[name]

    (pad,) = [n for n in fixed.graph.node if n.op_type == "Pad"]
    (lstm,) = [n for n in fixed.graph.node if n.op_type == "LSTM"]
    basis = weight("stft.forward_basis_buffer")[:, 0, :]                              # (130, 128)
    if basis.shape != (130, 128) or weights[pad.input[1]].tolist() != [0, 0, 0, 32]:
        raise RuntimeError(f"unexpected STFT: basis {basis.shape}, padding {weights[pad.input[1]].tolist()}")
    kernels = [(weight(f"encoder.{i}.reparam_conv.weight"), weight(f"encoder.{i}.reparam_conv.bias"))
               for i in range(4)]
    initializers: dict[str, np.ndarray] = {}
    nodes: list[onnx.NodeProto] = []

    def const(name: str, value) -> str:
        initializers[name] = np.array(value, np.int64) if isinstance(value, list) else np.asarray(value)
        return name

    def node(op: str, inputs: list[str], output: str | list[str], **attrs) -> str | list[str]:
        nodes.append(helper.make_node(op, inputs, [output] if isinstance(output, str) else output, **attrs))
        return output

    def taps(x: str, name: str, n_out: int, stride: int) -> str:
        """A kernel-3, padding-1 convolution's input: the three taps of every output frame side by side,
        (devices, n_out, 3 * channels)."""
        x = node("Pad", [x, "pad_frames"], f"{name}_padded")
        last = stride * (n_out - 1)   # the first tap of the last output frame, in the padded frames
        parts = [node("Slice", [x, const(f"{name}_from{k}", [k]), const(f"{name}_to{k}", [k + last + 1]), "axis1",
                                const(f"stride{stride}", [stride])], f"{name}_tap{k}") for k in range(3)]
        return node("Concat", parts, f"{name}_taps", axis=2)

    def layer(x: str, name: str, kernel: np.ndarray, bias: np.ndarray, taps_used=slice(0, 3)) -> str:
        """``Relu(x @ kernel + bias)`` with ``x`` (rows, taps * channels) and the kernel (out, channels, 3)
        reshaped to match (tap-major rows)."""
        w = kernel[:, :, taps_used].transpose(2, 1, 0).reshape(-1, kernel.shape[0])
        x = node("Reshape", [x, const(f"{name}_rows", [-1, w.shape[0]])], f"{name}_in")
        return node("Relu", [node("Gemm", [x, const(f"{name}_w", w), const(f"{name}_b", bias)], f"{name}_gemm")],
                    name)

    const("pad_frames", [0, 1, 0, 0, 1, 0])
    const("axis0", [0])
    const("axis1", [1])
    x = node("Pad", ["input", pad.input[1]], "padded", mode="reflect")              # (devices, 320)
    initializers[pad.input[1]] = weights[pad.input[1]]
    x = node("Reshape", [x, const("hops", [0, 5, 64])], "hops64")                     # (devices, 5, 64)
    first = node("Slice", [x, const("zero", [0]), const("four", [4]), "axis1"], "hops_first")
    second = node("Slice", [x, const("one", [1]), const("five", [5]), "axis1"], "hops_second")
    x = node("Concat", [first, second], "stft_frames", axis=2)                        # (devices, 4, 128)
    x = node("Reshape", [x, const("rows128", [-1, 128])], "stft_rows")
    x = node("MatMul", [x, const("stft_basis", basis.T.copy())], "stft")             # (devices * 4, 130)
    real = node("Slice", [x, "zero", const("half", [65]), "axis1"], "stft_real")
    imag = node("Slice", [x, "half", const("all", [130]), "axis1"], "stft_imag")
    power = node("Add", [node("Mul", [real, real], "real2"), node("Mul", [imag, imag], "imag2")], "power")
    x = node("Reshape", [node("Sqrt", [power], "magnitude"), const("frames65", [-1, 4, 65])], "spectrum")
    x = layer(taps(x, "enc0", 4, 1), "enc0", *kernels[0])                              # (devices * 4, 128)
    x = node("Reshape", [x, const("frames128", [-1, 4, 128])], "enc0_frames")
    x = layer(taps(x, "enc1", 2, 2), "enc1", *kernels[1])                              # (devices * 2, 64)
    x = layer(x, "enc2", *kernels[2], taps_used=slice(1, 3))   # one output frame: (zero, frame 0, frame 1)
    x = layer(x, "enc3", *kernels[3], taps_used=slice(1, 2))   # one frame: the kernel's centre
    x = node("Unsqueeze", [x, "axis0"], "lstm_in")                                      # (1, devices, 128)
    h0 = node("Slice", ["state", "zero", "one", "axis0"], "h0")
    c0 = node("Slice", ["state", "one", const("two", [2]), "axis0"], "c0")
    for i in (1, 2, 3):
        initializers[lstm.input[i]] = weights[lstm.input[i]]
    node("LSTM", [x, lstm.input[1], lstm.input[2], lstm.input[3], "", h0, c0], ["", "h", "c"], hidden_size=128)
    node("Concat", ["h", "c"], "stateN", axis=0)
    x = node("Relu", [node("Squeeze", ["h", "axis0"], "h_rows")], "decoder_in")
    decoder_w, decoder_b = weight("decoder.decoder.2.weight"), weight("decoder.decoder.2.bias")
    node("Sigmoid", [node("Gemm", [x, const("decoder_w", decoder_w[:, :, 0].T.copy()), const("decoder_b", decoder_b)],
                          "logit")], "output")
    graph = helper.make_graph(
        nodes, "silero_vad_8k",
        [helper.make_tensor_value_info("input", onnx.TensorProto.FLOAT, ["devices", WINDOW]),
         helper.make_tensor_value_info("state", onnx.TensorProto.FLOAT, [2, "devices", 128])],
        [helper.make_tensor_value_info("output", onnx.TensorProto.FLOAT, ["devices", 1]),
         helper.make_tensor_value_info("stateN", onnx.TensorProto.FLOAT, [2, "devices", 128])],
        [numpy_helper.from_array(np.ascontiguousarray(v), k) for k, v in initializers.items()])
    model = helper.make_model(graph, opset_imports=fixed.opset_import, ir_version=fixed.ir_version)
    onnx.checker.check_model(model)
    return model


def check_agrees(model: onnx.ModelProto) -> int:
    """:func:`compare` over the fixtures' devices; the number of windows compared."""
    import soxr
    x = []
    for name in ("meeting_table", "kitchen_noise"):
        for path in sorted((ROOT / "replay_fixtures" / name).glob("dev*.flac"))[:4]:
            y, fs = sf.read(path, dtype="float32", frames=int(6.0 * 48000))
            x.append(soxr.resample(y if y.ndim == 1 else y.mean(axis=1), fs, RATE_HZ)[:int(5.0 * RATE_HZ)])
    x = np.stack([np.pad(y, (0, int(5.0 * RATE_HZ) - len(y))) for y in x]).astype(np.float32)
    return len(compare(_session(onnx.load(str(SOURCE))), _session(model), x))


def main() -> int:
    if onnx is None:
        print("tools/silero_8k.py needs onnx and onnxsim: pip install -e \".[tools]\"", file=sys.stderr)
        return 1
    model = as_matrix_products(fix_rate(onnx.load(str(SOURCE))))
    n = check_agrees(model)
    onnx.save(model, str(TARGET))
    print(f"wrote {TARGET.relative_to(ROOT)} ({TARGET.stat().st_size} bytes, {len(model.graph.node)} nodes); "
          f"speech probabilities within {MAX_PROBABILITY_DIFF:g} of {SOURCE.name}'s and the same decisions over "
          f"{n} windows of 8 devices")
    return 0


if __name__ == "__main__":
    sys.exit(main())
