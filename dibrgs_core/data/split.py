"""Which views train and which are held out, and what views are called.

A view id is its photo's file stem (or, for a camera rig's like-named photos, its path,
:func:`view_ids`); the split comes from ``--train`` / ``--test``, ``split.json`` or
:func:`default_split` (:func:`make_split`).
"""
from __future__ import annotations

import json
import math
from pathlib import Path, PurePosixPath
from typing import TYPE_CHECKING, Iterable, Sequence

from ..common.errors import InputError
from ..common.limits import MIN_TRAIN_VIEWS

if TYPE_CHECKING:
    from .scene import Scene

SPLIT_FILE = "split.json"
TRAIN_ALL = "all"  # --train all: every view trains (but those --test names)
TEST_NONE = "none"  # --test none: nothing held out


def orbit_ids(ids: Sequence[str]) -> list[str]:
    """The orbit views among ``ids``: all but the near-nadir view 000 of a 21-view LEVIR scene."""
    ids = sorted(ids)
    if len(ids) == 21 and ids[0] == "000":
        return ids[1:]
    return list(ids)


def default_split(ids: Sequence[str], n_train: int = 3) -> tuple[list[str], list[str]]:
    """The split without ``split.json`` or ``--train``: ``n_train`` evenly spaced views (indices
    ``ceil(i * n / n_train)`` in name order) train, the others test.

    For a 21-view LEVIR-NVS scene the near-nadir view 000 is left out of both and the 20 orbit
    views give the paper's protocol: train 001, 008, 015 (indices 0, 7, 14), test the other 17.
    Any other scene (COLMAP, a folder of photos) uses all its views in name order: 9 photos give
    training views 1, 4 and 7 (indices 0, 3, 6)."""
    orbit = orbit_ids(ids)
    if len(orbit) < 2:
        raise ValueError("need at least 2 views for a train/test split")
    n_train = min(n_train, len(orbit) - 1)
    idx = sorted({math.ceil(i * len(orbit) / n_train) for i in range(n_train)})
    train = [orbit[i] for i in idx]
    return train, [i for i in orbit if i not in train]


def match_names(names: Iterable[str | int], ids: Sequence[str], where: str | Path | None, what: str) -> list[str]:
    """View ids of ``names``: exact ids, file names (``DJI_0019.png`` for ``DJI_0019``), paths in a
    rig's folders (``left/0001.jpg`` or ``left/0001`` for ``left_0001``) or LEVIR numbers (``8``
    for ``008``). ``InputError`` naming ``where`` lists any name not in the scene."""
    from .images import IMAGE_EXTS

    known = set(ids)
    out, bad = [], []
    for n in names:
        s = str(n).strip()
        p = Path(s)
        cands = [s, p.stem if p.suffix.lower() in IMAGE_EXTS else s, _norm_id(s),
                 path_id(s) if p.suffix.lower() in IMAGE_EXTS else s.replace("\\", "/").replace("/", "_")]
        hit = next((c for c in cands if c in known), None)
        if hit is None:
            bad.append(s)
        elif hit not in out:
            out.append(hit)
    if bad:
        shown = ", ".join(list(ids)[:12]) + (", ..." if len(ids) > 12 else "")
        raise InputError(where, f"{what}: {', '.join(map(repr, bad))} not in the scene (its views: {shown})")
    return out


def _only(names: Iterable[str | int], word: str, ids: Sequence[str]) -> bool:
    """Whether ``names`` is the one keyword ``word`` (any case) in a scene with no view of that name."""
    return [str(n).strip().lower() for n in names] == [word] and word not in {i.lower() for i in ids}


def read_split_file(path: Path) -> tuple[list | None, list | None]:
    """The ``train`` / ``test`` name lists of a ``split.json`` (``InputError`` naming it when malformed)."""
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise InputError(path, f"unreadable split file ({e}); expected {{\"train\": [names], \"test\": [names]}}") from None
    if not isinstance(data, dict) or not ({"train", "test"} & set(data)):
        raise InputError(path, 'expected an object {"train": [names], "test": [names]}')
    out = []
    for key in ("train", "test"):
        v = data.get(key)
        if v is not None and (not isinstance(v, list) or not all(isinstance(x, (str, int)) for x in v)):
            raise InputError(path, f'"{key}" must be a list of view names')
        out.append(v)
    return out[0], out[1]


def make_split(root: Path, ids: Sequence[str], train_ids: Iterable[str] | None,
               test_ids: Iterable[str] | None = None,
               layout: tuple[list[str], list[str], str] | None = None) -> tuple[list[str], list[str], str]:
    """Train and test ids of a scene, and where they came from.

    In order: ``train_ids`` / ``test_ids`` (the ``--train`` / ``--test`` options; each overrides
    its own part), then ``ROOT/split.json`` (``{"train": [...], "test": [...]}``, names with or
    without extension), then the ``layout``'s own (train, test, source) when it has one (a
    transforms layout's part files), then :func:`default_split`. A part not given explicitly comes from the
    next source, less the views the explicit part names. ``train_ids`` ``["all"]`` (in a scene
    with no view of that name) trains on every view but those of ``test_ids``, and holds out
    only those (none without them); ``test_ids`` ``["none"]`` holds nothing out. A name not in
    the scene is an ``InputError``, as is a view in both parts.
    """
    root = Path(root)
    src: list[str] = []
    train_ids = None if train_ids is None else list(train_ids)
    every = train_ids is not None and _only(train_ids, TRAIN_ALL, ids)
    train = match_names(train_ids, ids, None, "--train") if train_ids is not None and not every else None
    nothing = test_ids is not None and _only(test_ids, TEST_NONE, ids)
    test = [] if nothing else match_names(test_ids, ids, None, "--test") if test_ids is not None else None
    if every:
        train, test = [i for i in ids if i not in (test or [])], test or []
        src.append(f"--train {TRAIN_ALL}")
    elif train is not None:
        src.append("--train")
    if test_ids is not None:
        src.append("--test")
    split_file = root / SPLIT_FILE
    if split_file.exists() and not split_file.is_file():
        raise InputError(split_file, "is not a file; split.json must be a JSON file (or absent)")
    if (train is None or test is None) and split_file.is_file():
        f_train, f_test = read_split_file(split_file)
        used = False
        # An explicit part wins over the file's other part; the file's own two parts must not overlap.
        if train is None and f_train is not None:
            train = [i for i in match_names(f_train, ids, split_file, "train") if i not in (test or [])]
            used = True
        if test is None and f_test is not None:
            test = [i for i in match_names(f_test, ids, split_file, "test")
                    if train_ids is None or i not in train]
            used = True
        if used:
            src.append(str(split_file))
    if (train is None or test is None) and layout is not None:
        if train is None:
            train = [i for i in layout[0] if i not in (test or [])]
        if test is None:
            test = [i for i in layout[1] if train_ids is None or i not in train]
        src.append(layout[2])
    if train is None or test is None:
        if train is None:
            d_train, _ = default_split(ids)
            train = [i for i in d_train if i not in (test or [])]
            if test is None:
                test = [i for i in orbit_ids(ids) if i not in train]
        else:
            test = [i for i in orbit_ids(ids) if i not in train]
        src.append("default (LEVIR-NVS 3-view protocol)" if len(ids) == 21 and sorted(ids)[0] == "000"
                   else "default (3 evenly spaced views in name order)")
    both = sorted(set(train) & set(test))
    if both:
        where = None if train_ids is not None and test_ids is not None else (
            split_file if str(split_file) in src else root)
        raise InputError(where, f"views {both} are in both the training and the test set")
    if not train:
        raise InputError(root, "the split leaves no training view")
    return train, test, " + ".join(src)


def path_id(name: str) -> str:
    """An image's path within its image folder, without the extension, folders joined by ``_``
    (``left/0001.jpg`` -> ``left_0001``): the view id when file names repeat across folders."""
    p = PurePosixPath(name.replace("\\", "/"))
    return "_".join(p.parent.parts + (p.stem,))


def view_ids(names: Sequence[str]) -> dict[str, str]:
    """The view id of each image name of a model (names relative to its image folder): the file's
    stem (``DJI_0019.png`` -> ``DJI_0019``), or, when stems repeat (a camera rig writing the same
    file names into a folder per camera), :func:`path_id` for every view. ``ValueError`` names two
    images that still share an id."""
    stems = [PurePosixPath(n.replace("\\", "/")).stem for n in names]
    ids = stems if len(set(stems)) == len(stems) else [path_id(n) for n in names]
    seen: dict[str, str] = {}
    for n, i in zip(names, ids):
        if i in seen:
            raise ValueError(f"images {seen[i]} and {n} share the view id {i!r}")
        seen[i] = n
    return dict(zip(names, ids))


def _norm_id(i: str | int) -> str:
    """Accept 8 or "8" or "008" for view 008."""
    s = str(i)
    return f"{int(s):03d}" if s.isdigit() and len(s) < 3 else s


def require_train_views(scene: "Scene", minimum: int = MIN_TRAIN_VIEWS) -> None:
    """``InputError`` unless the scene's split has ``minimum`` training views: SfM with known poses,
    the plane sweep and the IBR features all work between training views, and a single view
    trains a model that only reproduces it."""
    if len(scene.train) < minimum:
        raise InputError(scene.root, f"{len(scene.train)} training view ({', '.join(scene.train) or 'none'}; "
                                     f"split from {scene.split_source}): DIBR-GS and the 3DGS baseline need at "
                                     f"least {minimum}; name more with --train or in {SPLIT_FILE}")
