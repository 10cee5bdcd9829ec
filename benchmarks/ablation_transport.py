"""Move the ablation's work folder to a GPU machine and its trained rows back, small.

``benchmarks/ablation.py --phase features`` fills a work folder on one machine; ``--phase train``
may run on another that is reached through a size limit. This packs what training and prediction
need (training sets, prepared objects, recorded test observations; not the images) and brings the
trained rows back::

    python benchmarks/ablation_transport.py pack WORK PACK          # after --phase features
    python benchmarks/ablation_transport.py unpack PACK WORK        # before --phase train
    python benchmarks/ablation_transport.py pack-models WORK OUT    # after --phase train
    python benchmarks/ablation_transport.py unpack-models OUT WORK  # before --phase score

``pack`` writes each ``train_set_KEY.safetensors`` as ``train_set_KEY.safetensors.xz`` with its
float tensors in float16 (a fifth of the float32 size: the query half of every instance repeats
per object, and xz's window, unlike zlib's 32 KiB, reaches back to it; the rounding, relative
5e-4, is the only loss), each ``test_observations_*.safetensors`` the same way but exact, and
``objects/`` as ``objects.tar.xz``. ``unpack`` restores the safetensors files (float32 again, same
names and keys) and ``objects/``, so the train phase finds its cache.

``pack-models`` writes the row folders under ``WORK/rows`` (``LABEL/NAME``: ``config.json``,
``model.safetensors``, ``train.json`` and ``predictions.csv`` when predicted) as one gzip tar
split into ``models.partNN`` files of at most 15 MiB; ``--only PATTERN ...`` keeps the rows whose
``LABEL/NAME`` matches a pattern, and weights over ``--max-weights-mib`` (default 16; the ``paper``
preset's are 166 MiB) stay behind, so such a row comes back with its predictions alone.
``unpack-models`` extracts the parts under ``WORK/rows``.
"""

from __future__ import annotations

import argparse
import fnmatch
import io
import json
import lzma
import tarfile
from pathlib import Path

import torch
from safetensors.torch import load, load_file, save, save_file

PART_BYTES = 15 * 2**20
ROW_FILES = ("config.json", "model.safetensors", "train.json", "predictions.csv")


def pack(work: Path, out: Path) -> list[Path]:
    """Write the training sets, the test observations and the prepared objects of ``work``."""
    sets = sorted(work.glob("train_set_*.safetensors"))
    observations = sorted(work.glob("test_observations_*.safetensors"))
    if not sets or not observations or not (work / "objects").is_dir():
        raise SystemExit(
            f"{work} lacks training sets, observations or objects/: run --phase features"
        )
    out.mkdir(parents=True, exist_ok=True)
    written = [_pack_tensors(p, out, half=True) for p in sets]
    written += [_pack_tensors(p, out, half=False) for p in observations]
    target = out / "objects.tar.xz"
    with tarfile.open(target, "w:xz") as tar:
        tar.add(work / "objects", arcname="objects")
    return [*written, target]


def unpack(pack_dir: Path, work: Path) -> list[Path]:
    """Restore the safetensors files and ``objects/`` of a :func:`pack` in ``work``."""
    blobs = sorted(pack_dir.glob("*.safetensors.xz"))
    if not blobs or not (pack_dir / "objects.tar.xz").is_file():
        raise SystemExit(f"{pack_dir} is not a pack: no *.safetensors.xz or objects.tar.xz")
    work.mkdir(parents=True, exist_ok=True)
    written = []
    for path in blobs:
        raw = lzma.decompress(path.read_bytes())
        metadata = _metadata(raw)
        dtypes = json.loads(metadata.pop("dtypes"))
        tensors = {k: v.to(getattr(torch, dtypes[k])) for k, v in load(raw).items()}
        target = work / path.name.removesuffix(".xz")
        save_file(tensors, str(target), metadata=metadata or None)
        written.append(target)
    with tarfile.open(pack_dir / "objects.tar.xz", "r:xz") as tar:
        tar.extractall(work, filter="data")
    return [*written, work / "objects"]


def pack_models(
    work: Path, out: Path, *, only: list[str] | None = None, max_weights_mib: float = 16.0
) -> list[Path]:
    """Write the rows saved under ``work/rows`` as ``models.partNN`` files in ``out``.

    Raises:
        SystemExit: no row matches.
    """
    folders = sorted(p.parent for p in (work / "rows").glob("*/*/train.json"))
    names = {f: f"{f.parent.name}/{f.name}" for f in folders}
    if only:
        folders = [f for f in folders if any(fnmatch.fnmatch(names[f], pat) for pat in only)]
    if not folders:
        raise SystemExit(f"no trained row under {work / 'rows'} matches {only or '*'}")
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as tar:
        for folder in folders:
            for name in ROW_FILES:
                path = folder / name
                if not path.is_file():
                    continue
                mib = path.stat().st_size / 2**20
                if name == "model.safetensors" and mib > max_weights_mib:
                    print(f"{names[folder]}: its {mib:.0f} MiB of weights stay behind")
                    continue
                tar.add(path, arcname=f"{names[folder]}/{name}")
    blob = buffer.getvalue()
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for i, start in enumerate(range(0, len(blob), PART_BYTES)):
        target = out / f"models.part{i:02d}"
        target.write_bytes(blob[start : start + PART_BYTES])
        written.append(target)
    return written


def unpack_models(pack_dir: Path, work: Path) -> list[Path]:
    """Extract :func:`pack_models`'s parts under ``work/rows``; returns the row folders."""
    parts = sorted(pack_dir.glob("models.part*"))
    if not parts:
        raise SystemExit(f"{pack_dir} holds no models.partNN files")
    rows = work / "rows"
    with tarfile.open(fileobj=io.BytesIO(b"".join(p.read_bytes() for p in parts))) as tar:
        members = tar.getnames()
        tar.extractall(rows, filter="data")
    return sorted({rows / Path(m).parent for m in members})


def _pack_tensors(path: Path, out: Path, *, half: bool) -> Path:
    """Write a safetensors file xz-compressed, its float tensors in float16 when ``half``."""
    from safetensors import safe_open

    with safe_open(str(path), "pt") as f:
        metadata = f.metadata() or {}
    tensors = load_file(str(path))
    dtypes = {k: str(v.dtype).removeprefix("torch.") for k, v in tensors.items()}
    if half:
        for k, v in tensors.items():
            if v.is_floating_point():
                tensors[k] = v.half()
                if not bool(torch.isfinite(tensors[k]).all()):
                    raise SystemExit(f"{path}: {k} does not fit in float16")
    target = out / f"{path.name}.xz"
    target.write_bytes(
        lzma.compress(save(tensors, metadata={**metadata, "dtypes": json.dumps(dtypes)}))
    )
    return target


def _metadata(raw: bytes) -> dict[str, str]:
    """The ``__metadata__`` of a safetensors file held in memory."""
    size = int.from_bytes(raw[:8], "little")
    return json.loads(raw[8 : 8 + size]).get("__metadata__", {})


def _report(paths: list[Path]) -> None:
    total = 0
    for p in paths:
        size = sum(f.stat().st_size for f in ([p] if p.is_file() else p.rglob("*")))
        total += size
        print(f"{size / 2**20:8.2f} MiB  {p}")
    print(f"{total / 2**20:8.2f} MiB  in all")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for name, src, dst in (
        ("pack", "work", "pack"),
        ("unpack", "pack", "work"),
        ("pack-models", "work", "out"),
        ("unpack-models", "out", "work"),
    ):
        p = sub.add_parser(name)
        p.add_argument(src, type=Path)
        p.add_argument(dst, type=Path)
        if name == "pack-models":
            p.add_argument("--only", nargs="+", default=None, help="LABEL/NAME patterns to keep")
            p.add_argument("--max-weights-mib", type=float, default=16.0)
    args = parser.parse_args()
    if args.command == "pack":
        _report(pack(args.work, args.pack))
    elif args.command == "unpack":
        _report(unpack(args.pack, args.work))
    elif args.command == "pack-models":
        _report(
            pack_models(args.work, args.out, only=args.only, max_weights_mib=args.max_weights_mib)
        )
    else:
        for folder in unpack_models(args.out, args.work):
            print(folder)


if __name__ == "__main__":
    main()
