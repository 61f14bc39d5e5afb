"""Static int8 quantisation (QDQ, per-channel weights) of an exported model, calibrated on renders.

The calibration frames are rendered scenes of the training distribution (never real-dev photos);
the metadata of the fp32 model is carried over, with the name and a note on the quantisation.

Two layers are laid out for onnxruntime's integer kernels rather than quantised as they are
(measured on the paper net at 640x480, 2 threads, per node):
- the first conv (one input channel) and the max-pool after it stay float32: an int8 conv with
  one input channel gathers its im2col one byte at a time (12 ms, against 4.6 ms for the float
  blocked kernel), and a uint8 pool outside the NHWC region is slower still (31 ms);
- a last conv with one output channel gets 15 zero filters and a Slice back to channel 0: the
  integer GEMM computes 16 columns anyway and its one-column path is the slow one (12 ms -> 3.4 ms
  + 1.1 ms for the Slice).
onnxruntime's QDQ propagation would move the first Quantize above the float pool again, so the
metadata asks the runtime to disable it (`disabled_optimizers`).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
import onnx
from onnx import helper, numpy_helper
from onnxruntime.quantization import CalibrationDataReader, CalibrationMethod, QuantFormat, QuantType, quantize_static

from .synth import SceneConfig, render_scene


class RenderReader(CalibrationDataReader):
    """Feeds `count` rendered 640x480 scenes, scaled as the runtime does (gray / 255)."""

    def __init__(self, count: int, seed: int) -> None:
        self._frames = iter(range(seed, seed + count))

    def get_next(self) -> dict | None:
        seed = next(self._frames, None)
        if seed is None:
            return None
        image = render_scene(np.random.default_rng(seed), SceneConfig()).image
        return {"image": (image.astype(np.float32) / 255)[None, None]}


GEMM_COLUMNS = 16  # output channels the integer GEMM computes at once
DISABLED_OPTIMIZERS = "QDQPropagationTransformer"


def widen_single_output_conv(proto: onnx.ModelProto) -> None:
    """Give a final one-channel Conv (+ Relu) GEMM_COLUMNS outputs, the extra filters zero, and
    slice channel 0 back out: the same scores, computed by the integer GEMM's fast path."""
    graph = proto.graph
    tail = next(n for n in graph.node if n.output[0] == graph.output[0].name)
    conv = next((n for n in graph.node if n.output[0] == tail.input[0]), None) if tail.op_type == "Relu" else tail
    inits = {i.name: i for i in graph.initializer}
    if conv is None or conv.op_type != "Conv" or numpy_helper.to_array(inits[conv.input[1]]).shape[0] != 1:
        return
    for name in conv.input[1:3]:
        array = numpy_helper.to_array(inits[name])
        wide = np.zeros((GEMM_COLUMNS, *array.shape[1:]), array.dtype)
        wide[0] = array[0]
        inits[name].CopyFrom(numpy_helper.from_array(wide, name))
    score, tail.output[0] = tail.output[0], tail.output[0] + "_wide"
    graph.initializer.extend(numpy_helper.from_array(np.array([v], np.int64), n)
                             for n, v in (("channel_start", 0), ("channel_end", 1), ("channel_axis", 1)))
    graph.node.append(helper.make_node("Slice", [tail.output[0], "channel_start", "channel_end", "channel_axis"],
                                       [score], name="channel0"))


def float_front(proto: onnx.ModelProto) -> list[str]:
    """Names of the first Conv and the Relu / MaxPool nodes straight after it: kept float32."""
    nodes = list(proto.graph.node)
    front = [nodes[0].name] if nodes[0].op_type == "Conv" else []
    for node in nodes[1:]:
        if not front or node.op_type not in ("Relu", "MaxPool"):
            break
        front.append(node.name)
    return front


def quantize(source: Path, out: Path, name: str, count: int = 32, seed: int = 800_000) -> None:
    fp32 = onnx.load(str(source))
    widen_single_output_conv(fp32)
    with tempfile.TemporaryDirectory() as tmp:
        widened, staged = Path(tmp) / "fp32.onnx", Path(tmp) / "int8.onnx"
        onnx.save(fp32, str(widened))
        quantize_static(str(widened), str(staged), RenderReader(count, seed), quant_format=QuantFormat.QDQ,
                        per_channel=True, activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                        calibrate_method=CalibrationMethod.MinMax, reduce_range=True,
                        nodes_to_exclude=float_front(fp32))
        proto = onnx.load(str(staged))
    meta = {p.key: p.value for p in fp32.metadata_props}
    # onnxruntime fuses QDQ pairs into integer kernels only at its ALL level (measured on the paper
    # net at 640x480, network only: 32 ms there, 95 ms at EXTENDED, 62 ms for fp32)
    meta.update(name=name, graph_optimization="all", disabled_optimizers=DISABLED_OPTIMIZERS,
                quantization=f"static int8 QDQ, per-channel 7-bit weights (reduce_range: no int16 saturation "
                             f"on CPUs without VNNI, so every CPU computes the same), MinMax on {count} renders "
                             f"(seeds {seed}+); first conv and pool float32, last conv widened to "
                             f"{GEMM_COLUMNS} outputs")
    del proto.metadata_props[:]
    helper.set_model_props(proto, meta)
    onnx.checker.check_model(proto)
    onnx.save(proto, str(out))


def main() -> None:
    parser = argparse.ArgumentParser(description="Quantise an exported CCDN model to int8 (QDQ).")
    parser.add_argument("model", type=Path)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--name", required=True)
    parser.add_argument("--count", type=int, default=32)
    args = parser.parse_args()
    quantize(args.model, args.out, args.name, args.count)


if __name__ == "__main__":
    main()
