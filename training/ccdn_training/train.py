"""Train CCDN on a bank of synthetic scenes, with checkpoints, resume, logs and a validation metric.

Two recipes:
  paper  SGD, momentum 0.9, lr 0.01, N(0, 0.1) weights and 0.1 biases (section 2.1). On our
         renders this recipe can die at once: the output ReLU goes dead and the loss's clip zeroes
         every gradient. Kept selectable for fidelity.
  adam   the same network, loss, init and staircase decay, with Adam at lr 1e-3: what trains.
Both use the staircase decay of eq. 6: lr_i = lr_0 * sigma ** floor(i / tau).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F

from .bank import SceneBank
from .loss import ccdn_loss
from .model import ARCHITECTURES

RECIPES = {
    "paper": {"optimizer": "sgd", "lr": 0.01, "momentum": 0.9},
    "adam": {"optimizer": "adam", "lr": 1e-3},
}


def staircase_lr(step: int, lr0: float, sigma: float, tau: int) -> float:
    """Eq. 6 of the paper."""
    return lr0 * sigma ** (step // tau)


def make_optimizer(model: torch.nn.Module, recipe: str) -> torch.optim.Optimizer:
    spec = RECIPES[recipe]
    if spec["optimizer"] == "sgd":
        return torch.optim.SGD(model.parameters(), lr=spec["lr"], momentum=spec["momentum"])
    return torch.optim.Adam(model.parameters(), lr=spec["lr"])


@torch.no_grad()
def validate(model: torch.nn.Module, bank: SceneBank, radius: float = 3.0, relative: float = 0.5, floor: float = 0.3) -> dict:
    """Precision, recall and F1 on full validation scenes of 5x5 local maxima above the runtime's
    threshold, max(relative * max score, floor): the balanced loss makes scores relative, not absolute."""
    model.eval()
    device = next(model.parameters()).device
    tp = fp = fn = 0
    errors = []
    for image, corners, ignore in zip(bank.images, bank.corners, bank.ignore):
        x = torch.from_numpy(image.astype(np.float32) / 255)[None, None].to(device)
        score = model(x.contiguous(memory_format=torch.channels_last))
        threshold = max(relative * float(score.max()), floor)
        peaks = (score == F.max_pool2d(score, 5, 1, 2)) & (score >= threshold)
        ys, xs = np.nonzero(peaks[0, 0].cpu().numpy())
        det = np.stack([xs, ys], 1).astype(np.float32)
        if len(ignore) and len(det):
            near_ignored = np.linalg.norm(det[:, None] - ignore[None], axis=2).min(1) < radius
            det = det[~near_ignored]
        if len(corners) and len(det):
            d = np.linalg.norm(det[:, None] - corners[None], axis=2)
            hit = d.min(1) < radius
            found = d.min(0) < radius
            tp += int(found.sum())
            fn += int((~found).sum())
            fp += int((~hit).sum())
            errors.extend(d.min(1)[hit].tolist())
        else:
            fn += len(corners)
            fp += len(det)
    model.train()
    precision = tp / max(tp + fp, 1)
    recall = tp / max(tp + fn, 1)
    f1 = 2 * precision * recall / max(precision + recall, 1e-9)
    return {"precision": precision, "recall": recall, "f1": f1, "pixel_error": float(np.mean(errors)) if errors else None}


def save_checkpoint(path: Path, **state) -> None:
    """Write atomically, so an interrupt never leaves a broken checkpoint."""
    tmp = path.with_suffix(".tmp")
    torch.save(state, tmp)
    tmp.replace(path)


def initial_weights(path: Path) -> dict[str, torch.Tensor]:
    """A state dict from a training checkpoint (.pt) or from an exported model (.onnx: its
    initializers carry the parameter names), e.g. to fine-tune a shipped model."""
    if path.suffix != ".onnx":
        return torch.load(path, map_location="cpu", weights_only=False)["model"]
    import onnx
    from onnx import numpy_helper

    return {t.name: torch.from_numpy(numpy_helper.to_array(t).copy()) for t in onnx.load(str(path)).graph.initializer}


def train(args: argparse.Namespace) -> None:
    torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    model = ARCHITECTURES[args.arch]()
    model.reset_parameters_paper()
    if args.init_from:  # warm start from another run's weights (recorded in the recipe)
        model.load_state_dict(initial_weights(args.init_from))
    model = model.to(args.device, memory_format=torch.channels_last)
    optimizer = make_optimizer(model, args.recipe)
    rng = np.random.default_rng(args.seed)
    step, best_f1 = 0, -1.0
    last = args.out / "last.pt"
    if args.resume and last.exists():
        state = torch.load(last, map_location=args.device, weights_only=False)
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        rng.bit_generator.state = state["rng"]
        step, best_f1 = state["step"], state["best_f1"]
        print(f"resumed at step {step}", flush=True)
    lr0 = args.lr or RECIPES[args.recipe]["lr"]
    recipe = {**RECIPES[args.recipe], "lr": lr0, "clip_grad": args.clip_grad,
              "recipe": args.recipe, "arch": args.arch, "batch": args.batch, "crop": args.crop,
              "sigma": args.sigma, "tau": args.tau, "weight_decay": args.weight_decay, "seed": args.seed,
              "bank": [str(b) for b in args.bank], "steps": args.steps,
              "init_from": str(args.init_from) if args.init_from else "paper N(0, 0.1) / 0.1"}
    (args.out / "recipe.json").write_text(json.dumps(recipe, indent=2))

    bank = SceneBank(*args.bank)
    val_bank = SceneBank(args.val_bank) if args.val_bank else None
    log = (args.out / "log.jsonl").open("a")
    t0, losses = time.time(), []
    while step < args.steps:
        lr = staircase_lr(step, lr0, args.sigma, args.tau)
        for group in optimizer.param_groups:
            group["lr"] = lr
        xs, ys = bank.crops(rng, args.batch, args.crop)
        x = torch.from_numpy(xs)[:, None].to(args.device).contiguous(memory_format=torch.channels_last)
        y = torch.from_numpy(ys)[:, None].to(args.device)
        loss = ccdn_loss(model(x, pre_activation=True), y, model, args.weight_decay)
        optimizer.zero_grad()
        loss.backward()
        if args.clip_grad:
            torch.nn.utils.clip_grad_norm_(model.parameters(), args.clip_grad)
        optimizer.step()
        losses.append(loss.item())
        step += 1
        if step % args.log_every == 0:
            entry = {"step": step, "loss": float(np.mean(losses)), "lr": lr, "elapsed_s": round(time.time() - t0, 1)}
            losses = []
            if val_bank is not None and (step % args.val_every == 0 or step == args.steps):
                entry["val"] = validate(model, val_bank)
                if entry["val"]["f1"] > best_f1:
                    best_f1 = entry["val"]["f1"]
                    save_checkpoint(args.out / "best.pt", model=model.state_dict(), arch=args.arch, step=step,
                                    val=entry["val"])
            log.write(json.dumps(entry) + "\n")
            log.flush()
            print(json.dumps(entry), flush=True)
        if step % args.checkpoint_every == 0 or step == args.steps:
            save_checkpoint(last, model=model.state_dict(), arch=args.arch, optimizer=optimizer.state_dict(),
                            rng=rng.bit_generator.state, step=step, best_f1=best_f1)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Train CCDN on rendered scenes (checkpoints in --out; --resume continues).")
    parser.add_argument("--bank", type=Path, nargs="+", required=True,
                        help="training scenes (.npz files from ccdn-render-bank, drawn from together)")
    parser.add_argument("--val-bank", type=Path, help="validation scenes (.npz)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--recipe", choices=sorted(RECIPES), default="adam")
    parser.add_argument("--arch", choices=sorted(ARCHITECTURES), default="paper",
                        help="paper: the paper's CCDN; fast: FastCCDN (model.py)")
    parser.add_argument("--steps", type=int, default=6000)
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--crop", type=int, default=96)
    parser.add_argument("--sigma", type=float, default=0.8, help="staircase decay rate (eq. 6)")
    parser.add_argument("--tau", type=int, default=1000, help="steps per decay stair (eq. 6)")
    parser.add_argument("--weight-decay", type=float, default=1e-4,
                        help="lambda of eq. 4 (paper: 0.01, which on our renders keeps the output near constant)")
    parser.add_argument("--lr", type=float, help="initial learning rate (default: the recipe's)")
    parser.add_argument("--clip-grad", type=float, default=1.0, help="gradient norm clip (0: off)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", default="cpu", help="torch device to train on, e.g. cuda (checkpoints load on any)")
    parser.add_argument("--log-every", type=int, default=50)
    parser.add_argument("--val-every", type=int, default=500)
    parser.add_argument("--checkpoint-every", type=int, default=250)
    parser.add_argument("--resume", action="store_true", help="continue from --out/last.pt")
    parser.add_argument("--init-from", type=Path,
                        help="start from these weights: a checkpoint (.pt) or an exported model (.onnx); fresh optimizer")
    train(parser.parse_args(argv))


if __name__ == "__main__":
    main()
