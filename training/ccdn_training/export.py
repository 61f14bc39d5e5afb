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
from torch import nn

from .model import ARCHITECTURES, parameter_count

OPSET = 17
PREPROCESSING = "gray_u8_div255"  # input = gray uint8 image / 255, float32, shape (N, 1, H, W)
OUTPUT_MEANING = "corner score per pixel, same HxW as the input; ~1 on the pixel nearest an inner corner, ~0 elsewhere"


def _git_commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def to_onnx(model: nn.Module, name: str, version: str, recipe: dict) -> onnx.ModelProto:
    """Build the ONNX graph of `model` from its layers(): input "image" (N,1,H,W) float32 -> output
    "score" (N,1,H,W). Initializers are named like the module's parameters."""
    nodes, inits = [], []
    x = "image"
    params = {id(p): n for n, p in model.named_parameters()}
    for i, layer in enumerate(model.layers()):
        kind, out = layer[0], f"{layer[0]}{i}"
        if kind == "conv":
            conv, relu = layer[1], layer[2]
            w_name, b_name = params[id(conv.weight)], params[id(conv.bias)]
            inits += [numpy_helper.from_array(conv.weight.detach().cpu().numpy().astype(np.float32), w_name),
                      numpy_helper.from_array(conv.bias.detach().cpu().numpy().astype(np.float32), b_name)]
            k = conv.weight.shape[-1]
            nodes.append(helper.make_node("Conv", [x, w_name, b_name], [out], kernel_shape=[k, k], pads=[k // 2] * 4,
                                          name=out))
            if relu:
                nodes.append(helper.make_node("Relu", [out], [out + "_relu"], name=out + "_relu"))
                out += "_relu"
        elif kind == "maxpool":
            _, k, stride, pads = layer
            nodes.append(helper.make_node("MaxPool", [x], [out], kernel_shape=[k, k], strides=[stride, stride],
                                          pads=list(pads), name=out))
        elif kind == "depth_to_space":
            nodes.append(helper.make_node("DepthToSpace", [x], [out], blocksize=layer[1], mode="CRD", name=out))
        elif kind == "relu":
            nodes.append(helper.make_node("Relu", [x], [out], name=out))
        else:
            raise ValueError(f"unknown layer {kind!r}")
        x = out
    nodes[-1].output[0] = "score"
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
        "input_multiple": str(getattr(model, "stride", 1)),  # H and W must be multiples of this
        "receptive_radius": str(receptive_radius(model)),  # px: how far a pixel's score sees
        # onnxruntime's ALL level lays convs out in blocks of 16 channels: a win when the channel
        # counts are multiples of 16 (FastCCDN), a loss for the paper net's 20 (measured)
        "graph_optimization": "all" if all(c.out_channels % 16 == 0 for c in model.convs()[:-1]) else "extended",
    }
    helper.set_model_props(proto, meta)
    onnx.checker.check_model(proto, full_check=True)
    return proto


def receptive_radius(model: nn.Module) -> int:
    """How many pixels beyond itself one output pixel depends on, from the layer list."""
    radius, scale = 0, 1
    for layer in model.layers():
        if layer[0] == "conv":
            radius += (layer[1].weight.shape[-1] // 2) * scale
        elif layer[0] == "maxpool":
            radius += (layer[1] - 1) * scale
            scale *= layer[2]
        elif layer[0] == "depth_to_space":
            radius += layer[1] - 1
    return radius


def load_checkpoint(path: Path) -> nn.Module:
    state = torch.load(path, map_location="cpu", weights_only=False)
    model = ARCHITECTURES[state.get("arch", "paper")]()
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
