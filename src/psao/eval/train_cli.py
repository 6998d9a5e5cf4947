"""`psao train mlp|nnao|aogan ...`: train a learned AO baseline and write its weights file.

    psao train mlp SCENE --grid GRID.npz --out mlp.npz      # MLP baking: one network per object of SCENE
    psao train nnao SCENE... --out nnao.npz                 # NNAO: one network for every scene
    psao train aogan SCENE... --out aogan.npz               # AOGAN (PyTorch): one generator for every scene

Training is numpy (AOGAN: PyTorch) on the CPU and seeded: the same command gives the same weights. With --json the last
stdout line is a JSON summary (seconds, weight bytes, first and last loss).
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from psao.options import DefaultsFormatter, default
from psao.eval.errors import EvalError
from psao.eval.learn.aogan_train import AoganDataSettings, AoganTrainSettings
from psao.eval.learn.mlp_train import MlpTrainSettings
from psao.eval.learn.nnao_train import NnaoDataSettings, NnaoTrainSettings


def add_arguments(p) -> None:
    sub = p.add_subparsers(dest="method", required=True, metavar="METHOD")
    m = sub.add_parser("mlp", formatter_class=DefaultsFormatter, help="MLP AO baking (Erra et al.): per-object networks from a baked grid's AO points")
    m.add_argument("scene", metavar="SCENE")
    m.add_argument("--grid", required=True, metavar="FILE", help="baked grid of SCENE (psao bake)")
    m.add_argument("--out", required=True, type=Path, metavar="FILE", help="weights file to write (.npz)")
    m.add_argument("--steps", type=int, default=default(MlpTrainSettings, "steps"), help="Adam steps")
    m.add_argument("--points", type=int, default=default(MlpTrainSettings, "points"), help="training points per object")
    m.add_argument("--seed", type=int, default=default(MlpTrainSettings, "seed"))
    m.add_argument("--json", action="store_true", help="print a JSON summary as the last line")

    n = sub.add_parser("nnao", formatter_class=DefaultsFormatter, help="NNAO (Holden et al.): one network trained on G-buffers and RTAO at sampled pixels")
    n.add_argument("scenes", nargs="*", metavar="SCENE",
                   help="training scenes (without any: builtin:pavilion and builtin:playground, the example TOML scenes "
                        "kept out of the benchmark)")
    n.add_argument("--out", required=True, type=Path, metavar="FILE", help="weights file to write (.npz)")
    n.add_argument("--frames", type=int, default=default(NnaoDataSettings, "frames"), help="frames per scene")
    n.add_argument("--pixels", type=int, default=default(NnaoDataSettings, "pixels"), help="sampled pixels per frame")
    n.add_argument("--spp", type=int, default=default(NnaoDataSettings, "spp"), help="RTAO rays per sampled pixel")
    n.add_argument("--epochs", type=int, default=default(NnaoTrainSettings, "epochs"), help="passes over the data")
    n.add_argument("--steps", type=int, default=None, help="Adam steps instead of --epochs")
    n.add_argument("--seed", type=int, default=default(NnaoTrainSettings, "seed"))
    n.add_argument("--json", action="store_true", help="print a JSON summary as the last line")

    g = sub.add_parser("aogan", formatter_class=DefaultsFormatter, help="AOGAN, scaled down for CPU (needs PyTorch): attention U-Net on G-buffers, "
                                     "PatchGAN critic, dense RTAO")
    g.add_argument("scenes", nargs="*", metavar="SCENE", help="training scenes (default: as for nnao)")
    g.add_argument("--out", required=True, type=Path, metavar="FILE", help="weights file to write (.npz)")
    g.add_argument("--frames", type=int, default=default(AoganDataSettings, "frames"), help="frames per scene")
    g.add_argument("--size", default="x".join(map(str, default(AoganDataSettings, "size"))), metavar="WxH",
                   help="training frame size")
    g.add_argument("--spp", type=int, default=default(AoganDataSettings, "spp"), help="RTAO rays per pixel")
    g.add_argument("--steps", type=int, default=default(AoganTrainSettings, "steps"), help="generator updates")
    g.add_argument("--seed", type=int, default=default(AoganTrainSettings, "seed"))
    g.add_argument("--json", action="store_true", help="print a JSON summary as the last line")


def _positive(name: str, value: int) -> None:
    if value < 1:
        raise EvalError(f"--{name} must be >= 1, got {value}")


def _progress(quiet: bool):
    start = time.perf_counter()
    last = [0.0]

    def report(step: int, total: int, loss: float) -> None:
        now = time.perf_counter()
        if not quiet and (now - last[0] > 2.0 or step == total):
            last[0] = now
            print(f"[{now - start:6.1f} s] step {step}/{total}, loss {loss:.5f}", file=sys.stderr)
    return report


def run(args) -> int:
    if args.method == "mlp":
        return run_mlp(args)
    if args.method == "nnao":
        return run_nnao(args)
    if args.method == "aogan":
        return run_aogan(args)
    raise EvalError(f"unknown training method {args.method!r}")


def run_mlp(args) -> int:
    from psao.client.render.gridfile import check_scene, load_grid_file
    from psao.client.render.weights import save_weights
    from psao.eval.learn.mlp_train import MlpTrainSettings, train_mlp
    from psao.scene import load_scene

    _positive("steps", args.steps)
    _positive("points", args.points)
    scene = load_scene(args.scene)
    grid = load_grid_file(args.grid)
    check_scene(grid, scene, args.grid)
    settings = MlpTrainSettings(steps=args.steps, points=args.points, seed=args.seed)
    result = train_mlp(grid, settings, progress=_progress(args.json))
    header = {"scene_hash": scene.content_hash(), "scene": scene.name, "hidden": list(settings.hidden),
              "steps": settings.steps, "points": settings.points, "seed": settings.seed, "grid": Path(args.grid).name}
    nbytes = save_weights(args.out, "mlp", result.arrays, header)
    summary = {"method": "mlp", "scene": scene.name, "out": str(args.out), "weight_bytes": nbytes,
               "instances": len(grid.instances), "instances_trained": result.instances_trained,
               "seconds": round(result.seconds, 2), "loss_first": result.losses[0], "loss_last": result.losses[-1]}
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"wrote {args.out}: {nbytes:,} bytes of weights for {result.instances_trained} object(s), "
              f"loss {summary['loss_first']:.5f} -> {summary['loss_last']:.5f} in {result.seconds:.1f} s",
              file=sys.stderr)
    return 0


def run_nnao(args) -> int:
    from psao.client.render.weights import save_weights
    from psao.eval.learn.nnao_train import TRAINING_SCENES, NnaoDataSettings, NnaoTrainSettings, build_dataset, train_nnao
    from psao.scene import load_scene

    for name in ("frames", "pixels", "spp", "epochs"):
        _positive(name, getattr(args, name))
    if args.steps is not None:
        _positive("steps", args.steps)
    specs = list(args.scenes) or list(TRAINING_SCENES)
    scenes = [load_scene(s) for s in specs]
    data = NnaoDataSettings(frames=args.frames, pixels=args.pixels, spp=args.spp, seed=args.seed)
    t0 = time.perf_counter()
    quiet = args.json

    def data_progress(n: int) -> None:
        if not quiet:
            print(f"[{time.perf_counter() - t0:6.1f} s] {n:,} training pixels traced", file=sys.stderr)

    x, y = build_dataset(scenes, data, progress=data_progress)
    data_s = time.perf_counter() - t0
    train = NnaoTrainSettings(epochs=args.epochs, seed=args.seed)
    result = train_nnao(x, y, train, steps=args.steps, progress=_progress(quiet))
    header = {"trained_on": [s.name for s in scenes], "frames": data.frames, "pixels": data.pixels, "spp": data.spp,
              "epochs": train.epochs, "steps": len(result.losses), "seed": args.seed, "samples": int(len(y)),
              "data_s": round(data_s, 1), "train_s": round(result.seconds, 1)}
    nbytes = save_weights(args.out, "nnao", result.arrays, header)
    k = max(1, len(result.losses) // 20)
    summary = {"method": "nnao", "out": str(args.out), "weight_bytes": nbytes, "samples": int(len(y)),
               "trained_on": header["trained_on"], "data_s": header["data_s"], "train_s": header["train_s"],
               "loss_first": float(np.mean(result.losses[:k])), "loss_last": float(np.mean(result.losses[-k:]))}
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"wrote {args.out}: {nbytes:,} bytes, {len(y):,} pixels of {', '.join(header['trained_on'])}, loss "
              f"{summary['loss_first']:.5f} -> {summary['loss_last']:.5f}, {data_s:.0f} s data + {result.seconds:.0f} s "
              "training", file=sys.stderr)
    return 0


def run_aogan(args) -> int:
    from psao.client.errors import RenderError
    from psao.client.render.aogan_net import require_torch
    from psao.client.render.output import parse_size
    from psao.client.render.weights import save_weights
    from psao.eval.learn.aogan_train import AoganDataSettings, AoganTrainSettings, build_dataset, train_aogan
    from psao.eval.learn.nnao_train import TRAINING_SCENES
    from psao.scene import load_scene

    for name in ("frames", "spp", "steps"):
        _positive(name, getattr(args, name))
    try:
        require_torch()
        size = parse_size(args.size)
    except RenderError as exc:
        raise EvalError(str(exc)) from None
    if min(size) < 64:
        raise EvalError(f"--size {args.size}: frames must be at least 64x64")
    scenes = [load_scene(s) for s in (list(args.scenes) or list(TRAINING_SCENES))]
    t0 = time.perf_counter()
    quiet = args.json

    def data_progress(n: int) -> None:
        if not quiet:
            print(f"[{time.perf_counter() - t0:6.1f} s] {n} training frame(s) traced", file=sys.stderr)

    x, y = build_dataset(scenes, AoganDataSettings(frames=args.frames, size=size, spp=args.spp, seed=args.seed),
                         progress=data_progress)
    data_s = time.perf_counter() - t0
    result = train_aogan(x, y, AoganTrainSettings(steps=args.steps, seed=args.seed), progress=_progress(quiet))
    header = {"trained_on": [s.name for s in scenes], "frames": args.frames, "size": list(size), "spp": args.spp,
              "steps": args.steps, "seed": args.seed, "data_s": round(data_s, 1), "train_s": round(result.seconds, 1)}
    nbytes = save_weights(args.out, "aogan", result.arrays, header)
    k = max(1, len(result.losses) // 20)
    summary = {"method": "aogan", "out": str(args.out), "weight_bytes": nbytes, "trained_on": header["trained_on"],
               "data_s": header["data_s"], "train_s": header["train_s"],
               "dssim_first": float(np.mean(result.losses[:k])), "dssim_last": float(np.mean(result.losses[-k:]))}
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"wrote {args.out}: {nbytes:,} bytes, DSSIM {summary['dssim_first']:.4f} -> {summary['dssim_last']:.4f}, "
              f"{data_s:.0f} s data + {result.seconds:.0f} s training", file=sys.stderr)
    return 0
