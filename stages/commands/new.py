"""``cobgs new FOLDER``: a ready workflow for a folder of your own data.

It looks at the folder (which layout it is: photos in ``images/``, a COLMAP model, LLFF
``poses_bounds.npy``, a ``transforms.json``; which ``masks/<object>/`` folders it has),
then writes a workflow TOML with every choice it made written beside it as a comment, so
the next steps are ``cobgs run`` and ``cobgs report``. It opens every image's header (PIL):
unreadable and empty files are named and not counted, mixed sizes are reported, and photos
whose EXIF orientation asks for a rotation are refused with the fix
(:mod:`cobgs.data.images`). Nothing heavier (no torch) is imported.
"""

from __future__ import annotations

import os
import re
import sys
from pathlib import Path

_IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp")


def _images(folder: Path) -> list[Path]:
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in _IMAGE_SUFFIXES)


def detect(folder: Path) -> dict:
    """What the folder holds: kind, why, image count and size, mask objects."""
    from cobgs.data.formats import FORMATS, detect  # the readers' own detector (standard library only)

    layout = detect(folder)
    if layout is not None:
        kind, why = layout, FORMATS[layout].found
    elif _images(folder / "images"):
        kind, why = "images", "photos in images/ and no cameras: SfM (pycolmap) will find them"
    elif _images(folder):
        raise SystemExit(f"cobgs new: {folder} holds photos ({_images(folder)[0].name} ...) but no images/ "
                         "subfolder: move them into images/ (masks go to masks/<object>/, named after "
                         "the photos) and run this again")
    else:
        raise SystemExit(f"cobgs new: {folder} has no images/ folder, transforms.json, COLMAP model "
                         "or poses_bounds.npy: nothing to build a scene from")
    imgs, bad, sizes = _survey(_images(folder / "images"))
    objects = sorted(p.name for p in (folder / "masks").iterdir()
                     if p.is_dir() and _images(p)) if (folder / "masks").is_dir() else []
    _check_masks(folder, objects, [p.stem for p in imgs])
    size = max(sizes, key=lambda k: len(sizes[k])) if sizes else "?"
    return {"kind": kind, "why": why, "images": len(imgs), "size": size, "objects": objects,
            "unreadable": bad, "sizes": {k: len(v) for k, v in sizes.items()}}


def _survey(paths: list[Path]) -> tuple[list[Path], dict[str, str], dict[str, list[str]]]:
    """(readable images, {unreadable or empty file: why}, {"WxH": files}) from the headers.

    Raises:
        SystemExit: an image whose EXIF orientation asks for a rotation (the fix named).
    """
    from cobgs.data.images import check_upright, probe
    from cobgs.errors import DataError

    ok, bad, sizes = [], {}, {}
    for p in paths:
        try:
            if p.stat().st_size == 0:
                bad[p.name] = "empty file"
                continue
            w, h, _ = probe(p)
        except (OSError, DataError) as exc:
            bad[p.name] = str(exc).split(": ", 1)[-1][:120]
            continue
        ok.append(p)
        sizes.setdefault(f"{w}x{h}", []).append(p.name)
    try:
        check_upright(ok, "photo")
    except DataError as exc:
        raise SystemExit(f"cobgs new: {exc}") from None
    return ok, bad, sizes


def _check_masks(folder: Path, objects: list[str], stems: list[str]) -> None:
    """Each ``masks/<object>/`` folder, now rather than after SfM and training: its files stored
    upright (no EXIF orientation tag, as the photos) and at least one named after a photo.

    Raises:
        SystemExit: naming the folder, the tag, or examples of both names.
    """
    from cobgs.data.images import check_upright
    from cobgs.errors import DataError

    have = set(stems)
    for obj in objects:
        files = _images(folder / "masks" / obj)
        try:
            check_upright(files, "mask file")
        except DataError as exc:
            raise SystemExit(f"cobgs new: {exc}") from None
        if have and not any(f.stem in have for f in files):
            raise SystemExit(f"cobgs new: {folder / 'masks' / obj}: no mask file is named after a photo; a mask "
                             f"is masks/{obj}/<photo name>.png (e.g. {sorted(have)[0]}.png for images/"
                             f"{sorted(have)[0]}...), but the folder holds {[f.name for f in files[:3]]} and the "
                             f"photos are {sorted(have)[:3]}: rename the masks after their photos")


def _name(text: str) -> str:
    """A workflow / item name from free text: no separators, no control characters, no
    leading dot, at most 100 bytes (the pipeline's rules for value names)."""
    s = re.sub(r"[/\\,=\x00-\x1f\x7f]+", "_", text).strip().lstrip(".").strip()
    while len(s.encode("utf-8")) > 100:
        s = s[:-1].rstrip()
    return s or "scene"


def _unique_names(objects: list[str]) -> dict[str, str]:
    """object folder / prompt -> its item name: :func:`_name`, made unique (``a,b`` and
    ``a=b`` both clean to ``a_b``: the second becomes ``a_b_2``)."""
    out: dict[str, str] = {}
    used: set[str] = set()
    for obj in objects:
        base = name = _name(obj)
        k = 2
        while name in used:
            name = f"{base}_{k}"
            k += 1
        used.add(name)
        out[obj] = name
    return out


def _toml_str(text: str) -> str:
    """A TOML string value: :func:`_toml_key`, with ``${`` written ``$${`` (a literal ``${``
    for the workflow reader, which expands ``${NAME}`` in values, not in keys)."""
    return _toml_key(text.replace("${", "$${"))


def _toml_key(text: str) -> str:
    """A TOML basic string: backslash, quote and every control character escaped."""
    out = []
    for ch in text:
        if ch == "\\":
            out.append("\\\\")
        elif ch == '"':
            out.append('\\"')
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append({"\n": "\\n", "\t": "\\t", "\r": "\\r"}.get(ch, f"\\u{ord(ch):04x}"))
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def _comment(text: str) -> str:
    """Free text safe inside a one-line TOML comment (control characters shown escaped)."""
    return "".join(repr(ch)[1:-1] if ord(ch) < 0x20 or ord(ch) == 0x7F else ch for ch in text)


def workflow_text(folder: Path, info: dict, name: str, prompts: list[str], views_every: int) -> str:
    scene = _name(folder.name)
    lines = [
        f"# Written by `cobgs new {_comment(os.fspath(folder))}`: the choices below are cobgs new's; change "
        "any of them.",
        f"#   data: {_comment(os.fspath(folder))}",
        f"#   kind = {info['kind']!r}: {info['why']}",
        f"#   {info['images']} images" + (f", {info['size']}" if info["size"] != "?" else ""),
    ]
    if len(info.get("sizes") or {}) > 1:
        lines.append(f"#   mixed sizes: {_comment(', '.join(f'{n} x {k}' for k, n in info['sizes'].items()))} (SfM "
                     "takes each photo as it is; a mask must have its photo's aspect)")
    if info.get("unreadable"):
        shown = "; ".join(f"{k} ({v})" for k, v in list(info["unreadable"].items())[:5])
        lines.append(f"#   not counted, unreadable: {_comment(shown)}"
                     + (f" and {len(info['unreadable']) - 5} more" if len(info["unreadable"]) > 5 else "")
                     + " (SfM fails on them: remove them from images/)")
    if prompts:
        source = "onnx"
        objects = prompts
        lines.append(f"#   masks: text prompts {_comment(str(prompts))} -> Grounding DINO + SAM2 (two-stage), through the "
                     "ONNX exports in $COBGS_MODELS_DIR (`cobgs export-onnx sam2 ...` and `gdino ...`)")
    elif info["objects"]:
        source = "files"
        objects = info["objects"]
        lines.append(f"#   masks: from files, masks/<object>/ named after the photos: {_comment(str(objects))} "
                     "(any resolution; a pixel counts when it is >= 128: save masks as 0/255)")
    else:
        raise SystemExit(f"cobgs new: {folder} has no masks/<object>/ folder of masks named after the "
                         "photos; give them, or segment by text with --prompt \"a red mug\" (needs the ONNX "
                         "models: `cobgs export-onnx`)")
    lines += [
        f"#   held-out views: every {views_every}th image (not trained on; the report's PSNR and",
        "#   pictures use them; without ground-truth masks there is no mIoU, only PSNR and pictures)",
        "# Next:  cobgs run THIS.toml   then   cobgs report THIS.toml   (and cobgs export THIS.toml --to DIR)",
        "",
        "[workflow]",
        f"name = {_toml_str(name)}",
        f"description = {_toml_str(f'COB-GS on {folder.name} ({len(objects)} object(s))')}",
        'nested = { object = "scene" }',
        "",
        "[settings]",
        'device = "cpu"                 # or `--set device=cuda` on a machine with a GPU',
        "",
        "[params.dataset]",
        f"test_every = {views_every}",
        "",
        "[params.train]",
        "# The paper's 30 000-iteration 3DGS schedule: COB-GS's boundaries need it (docs/benchmarks/cost_cpu.md,",
        "# issue 57: no faster recipe measured so far loses no boundary mBIoU on every bench scene).",
        "# Faster: recipe = \"fast\" (a resolution schedule and a Gaussian budget over 12 000 iterations;",
        "# fern at 1008x756 on 2 CPU cores in 0.77 h instead of 2.95 h, at the cost of 0.6-3.7 points of",
        "# boundary mBIoU on three of make bench's five scenes). On a GPU the faithful recipe is minutes.",
        'recipe = "3dgs"',
        "",
    ]
    held = -(-info["images"] // views_every) if views_every else 0
    train_views = info["images"] - held
    short = _stage_length_for(train_views)
    if short:
        lines += [
            "[params.refine.cobgs]",
            f"# {train_views} training views: COB-GS's stages of 2 x {train_views} iterations would be shorter than the",
            f"# {short[1]} a split Gaussian's label needs to become foreground (docs/method.md §2, \"Few views\")",
            f"stage_length_views = {short[0]:g}",
            "",
        ]
    if info["kind"] == "images":
        lines += [
            "[params.sfm.options]",
            '# SIMPLE_RADIAL: COLMAP\'s default for photos from an unknown lens (undistorted afterwards,',
            '# masks too); use "SIMPLE_PINHOLE" for rendered or already undistorted images.',
            'camera_model = "SIMPLE_RADIAL"',
            "num_threads = 1                # repeatable (COLMAP on several threads is not)",
            "",
        ]
    lines += ["[params.masks]", f'source = "{source}"']
    if source == "onnx":
        lines.append('models_dir = "${COBGS_MODELS_DIR}"')
    from cobgs.data.formats import FORMATS

    st_default = FORMATS[info["kind"]].scene_type if info["kind"] in FORMATS else "360"  # as the dataset stage
    other = "forward" if st_default == "360" else "360"
    why = {"forward": "a forward-facing capture: δ 0.5, 6 mask stages",
           "360": "the camera goes around the object: δ 0.8, 4 mask stages"}
    lines += ["", f"[axes.scene.{_toml_key(scene)}]", f'kind = "{info["kind"]}"',
              f"path = {_toml_str(os.fspath(folder))}",
              f'# scene_type = "{other}"   # if {why[other]} (default for this kind: {st_default},',
              f"#                           {why[st_default]})", "",
              "[axes.method.cobgs]", "# peers, to compare: uncomment",
              '# [axes.method.nosplit]\n# refine = { method = "nosplit" }', ""]
    names = _unique_names(objects)
    for obj in objects:
        lines.append(f"[axes.object.{_toml_key(scene)}.{_toml_key(names[obj])}]")
        if source == "onnx":
            lines.append(f"prompt = {_toml_str(obj)}")
        elif names[obj] != obj:  # the folder's own name, which the item name could not keep
            lines.append(f"mask = {_toml_str(obj)}                # the folder masks/{_comment(obj)}/")
    return "\n".join(lines) + "\n"


def _stage_length_for(train_views: int):
    """(stage_length_views, iterations needed) where the default stages of 2V iterations are
    too short for ``train_views`` views, else None."""
    from cobgs.configs import RefineConfig

    cfg = RefineConfig()
    if train_views < 1 or not cfg.stages_too_short(train_views):
        return None
    return max(cfg.stage_length_views, cfg.min_stage_length_views(train_views)), cfg.steps_to_foreground()


def _check_loads(text: str, out: Path) -> str:
    """Why the workflow ``text`` would not load (as if saved at ``out``); "" when it loads."""
    import tempfile
    import tomllib

    try:
        tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        return f"invalid TOML: {exc}"
    from pipeline import WorkflowError, load_workflow
    from stages.registry import load_registry

    fd, probe = tempfile.mkstemp(prefix=".cobgs-new-", suffix=".toml", dir=out.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        # the model folder of text prompts may not exist yet: `cobgs run` asks for it
        env = {**os.environ, "COBGS_MODELS_DIR": os.environ.get("COBGS_MODELS_DIR") or "/models-set-later"}
        load_workflow(Path(probe), load_registry(), environ=env)
    except (WorkflowError, ValueError) as exc:
        return str(exc)
    finally:
        os.unlink(probe)
    return ""


def _new(args) -> int:
    folder = Path(args.folder).resolve()
    if not folder.is_dir():
        print(f"cobgs new: {folder} is not a folder", file=sys.stderr)
        return 2
    if args.name is not None and _name(args.name) != args.name:
        print(f"cobgs new: --name {args.name!r}: a workflow name holds no '/', '\\', ',', '=' or control "
              f"characters and does not start with a dot (at most 100 bytes); e.g. {_name(args.name)!r}",
              file=sys.stderr)
        return 2
    try:
        info = detect(folder)
        name = _name(args.name or folder.name)
        text = workflow_text(folder, info, name, list(args.prompt or []), args.test_every)
    except SystemExit as exc:
        print(exc, file=sys.stderr)
        return 2
    out = Path(args.out or f"{name}.toml")
    if out.is_dir():
        print(f"cobgs new: --out {out} is a folder; give the TOML file to write", file=sys.stderr)
        return 2
    if not out.parent.is_dir():
        print(f"cobgs new: --out {out}: the folder {out.parent} does not exist", file=sys.stderr)
        return 2
    if out.exists() and not args.force:
        print(f"cobgs new: {out} exists (pass --force to replace it)", file=sys.stderr)
        return 2
    problem = _check_loads(text, out)
    if problem:
        print(f"cobgs new: the workflow written for {folder} would not load ({problem}); nothing written",
              file=sys.stderr)
        return 2
    tmp = out.with_name(f".{out.name}.tmp-{os.getpid()}")
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, out)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        print(f"cobgs new: cannot write {out}: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {out}: kind {info['kind']!r}, {info['images']} images, "
          f"objects {list(args.prompt or info['objects'])}")
    if len(info["sizes"]) > 1:
        print(f"note: the photos have {len(info['sizes'])} sizes ("
              + ", ".join(f"{n} x {k}" for k, n in info["sizes"].items()) + ")")
    if info["unreadable"]:
        print(f"warning: {len(info['unreadable'])} file(s) in images/ are unreadable or empty and were not counted: "
              + "; ".join(f"{k} ({v})" for k, v in list(info["unreadable"].items())[:5])
              + ": remove them before `cobgs run` (SfM fails on them)", file=sys.stderr)
    print(f"next: cobgs run {out} && cobgs report {out}")
    return 0


def _every(text: str) -> int:
    import argparse

    try:
        k = int(text)
    except ValueError:
        k = -1
    if k < 0 or k == 1 or k > 1_000_000:
        raise argparse.ArgumentTypeError(f"expected 0 (hold out nothing) or an integer k >= 2 (every k-th image), "
                                         f"got {text!r}" + (": 1 would hold out every image" if k == 1 else ""))
    return k


def _prompt(text: str) -> str:
    import argparse

    if not text.strip():
        raise argparse.ArgumentTypeError("an empty text prompt finds nothing; name the object, e.g. --prompt "
                                         "\"a red mug\"")
    return text


def register(sub) -> None:
    p = sub.add_parser("new", help="write a ready workflow for a folder of your own data",
                       description="Look at FOLDER (photos in images/, or a COLMAP / LLFF / "
                       "transforms.json scene; masks/<object>/ folders) and write a workflow TOML "
                       "with the choices it made as comments. Then: cobgs run, cobgs report.")
    p.add_argument("folder", help="the data folder")
    p.add_argument("--prompt", action="append", metavar="TEXT", type=_prompt,
                   help="segment this object by text (Grounding DINO + SAM2; repeatable) instead of "
                   "masks/<object>/ files")
    p.add_argument("--name", help="workflow name (default: the folder's name)")
    p.add_argument("--out", help="TOML file to write (default: NAME.toml here)")
    p.add_argument("--test-every", type=_every, default=8,
                   help="hold out every k-th image (default 8; 0 = none; 1 would hold out every image)")
    p.add_argument("--force", action="store_true", help="replace an existing TOML file")
    p.set_defaults(func=_new)
