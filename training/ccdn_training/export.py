"""ONNX export of a trained CCDN checkpoint, with the metadata the runtime reads.

The graph is written node by node from the module's weights rather than traced: the two
one-sided max-pool paddings then live in MaxPool's own `pads` attribute (no Pad nodes, which cost
a copy of the feature map each), the opset is fixed, and batch, height and width are dynamic.
A parity test compares this graph with the PyTorch module.
"""

from __future__ import annotations

import argparse
import json
import subprocess
from pathlib import Path

import numpy as np
import onnx
import torch
from onnx import TensorProto, helper, numpy_helper

from .model import CCDN, parameter_count

OPSET = 17
PREPROCESSING = "gray_u8_div255"  # input = gray uint8 image / 255, float32, shape (N, 1, H, W)
OUTPUT_MEANING = "corner score per pixel, same HxW as the input; ~1 on the pixel nearest an inner corner, ~0 elsewhere"


def _git_commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def to_onnx(model: CCDN, name: str, version: str, recipe: dict) -> onnx.ModelProto:
    """Build the ONNX graph of `model`: input "image" (N,1,H,W) float32 -> output "score" (N,1,H,W)."""
    nodes, inits = [], []
    x = "image"
    pools = {1: [0, 0, 1, 1], 4: [1, 1, 0, 0]}  # after conv1: pad bottom/right; after conv4: top/left
    for i, conv in enumerate(model.convs(), start=1):
        w = conv.weight.detach().cpu().numpy().astype(np.float32)
        b = conv.bias.detach().cpu().numpy().astype(np.float32)
        inits += [numpy_helper.from_array(w, f"conv{i}.weight"), numpy_helper.from_array(b, f"conv{i}.bias")]
        k = w.shape[-1]
        p = k // 2
        nodes.append(helper.make_node("Conv", [x, f"conv{i}.weight", f"conv{i}.bias"], [f"conv{i}"],
                                      kernel_shape=[k, k], pads=[p, p, p, p], name=f"conv{i}"))
        out = "score" if i == 6 else f"relu{i}"
        nodes.append(helper.make_node("Relu", [f"conv{i}"], [out], name=f"relu{i}"))
        x = out
        if i in pools:
            nodes.append(helper.make_node("MaxPool", [x], [f"pool{i}"], kernel_shape=[2, 2], strides=[1, 1],
                                          pads=pools[i], name=f"pool{i}"))
            x = f"pool{i}"
    dims = ["batch", 1, "height", "width"]
    graph = helper.make_graph(
        nodes, "ccdn",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, dims)],
        [helper.make_tensor_value_info("score", TensorProto.FLOAT, dims)],
        initializer=inits,
    )
    proto = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="ccdn-training")
    proto.ir_version = 8
    meta = {
        "name": name,
        "version": version,
        "preprocessing": PREPROCESSING,
        "output": OUTPUT_MEANING,
        "recipe": json.dumps(recipe, sort_keys=True),
        "commit": _git_commit(),
        "parameters": str(parameter_count(model)),
    }
    helper.set_model_props(proto, meta)
    onnx.checker.check_model(proto, full_check=True)
    return proto


def load_checkpoint(path: Path) -> CCDN:
    model = CCDN()
    state = torch.load(path, map_location="cpu", weights_only=False)
    model.load_state_dict(state["model"])
    return model.eval()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Export a CCDN checkpoint to ONNX with metadata.")
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--name", default="paper")
    parser.add_argument("--version", default="1.0.0")
    parser.add_argument("--recipe", type=Path, help="recipe.json written by the training run")
    args = parser.parse_args(argv)
    recipe = json.loads(args.recipe.read_text()) if args.recipe else {}
    proto = to_onnx(load_checkpoint(args.checkpoint), args.name, args.version, recipe)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(proto, args.out)


if __name__ == "__main__":
    main()
