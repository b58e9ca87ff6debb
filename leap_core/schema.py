"""Class schemas: the ordered class list of a labeling project, read from editable YAML files.

A schema fixes, for each class index 0..C-1: its name, display colour, the text prompts given to the
open-vocabulary detector (docs/METHOD.md stage A, "prompt expansion"), the raw id written to exported
``.label`` files, the raw ground-truth ids that count as this class when evaluating (SemanticKITTI
``learning_map`` semantics) and a coarse category for category mIoU.

File format (``projects/<name>.yaml``)::

    name: semantickitti
    description: free text
    classes:
      - name: car
        color: [100, 150, 245]      # RGB 0..255, or "#6496f5"
        prompts: [car, automobile]  # >= 1
        export_id: 10               # 1..65535; 0 is reserved for "unlabeled" in exports
        gt_ids: [10, 252]           # optional
        category: vehicle           # optional, default "other"
        negative_prompts: []        # optional
        thing: true                 # optional: a countable object (tracked, given instance ids)
        moving_id: 252              # optional: raw id exported for its points while it moves (a thing)
    pipeline: {}                    # optional config overrides, see leap_core.presets.load_preset

Every problem raises :class:`~leap_core.errors.SchemaError` with one line naming the file and the entry,
e.g. ``projects/x.yaml: classes[3] 'pole': color must be 3 integers 0..255``.
"""

from __future__ import annotations

import dataclasses
import difflib
import numbers
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any, TypeGuard

import numpy as np
import numpy.typing as npt
import yaml

from leap_core.errors import SchemaError
from leap_core.io_utils import atomic_write_bytes
from leap_core.types import UNLABELED

CATEGORIES: tuple[str, ...] = ("vehicle", "human", "flat", "construction", "nature", "object")
"""The six coarse categories of KITTI-360 style category mIoU. Other category names are allowed too."""

MAX_RAW_ID = 0xFFFF
"""Raw ids live in the low 16 bits of a ``.label`` value."""

# Grounding DINO splits the prompt string into phrases at these characters, so a prompt containing one
# would silently become two phrases and its token columns would no longer belong to one prompt.
_PHRASE_SEPARATORS = (".", "?")

_CLASS_KEYS = (
    "name",
    "color",
    "prompts",
    "export_id",
    "gt_ids",
    "category",
    "negative_prompts",
    "thing",
    "moving_id",
)
_REQUIRED_CLASS_KEYS = ("name", "color", "prompts", "export_id")
_TOP_KEYS = ("name", "description", "classes")
_PROJECT_KEYS = (*_TOP_KEYS, "pipeline")
_HEX_COLOR = re.compile(r"^#([0-9a-fA-F]{6})$")
_SCHEMA_NAME = re.compile(r"^[A-Za-z0-9_-]+$")

SEMANTICKITTI_THINGS: dict[tuple[str, int], int | None] = {
    ("car", 10): 252,
    ("bicycle", 11): None,
    ("motorcycle", 15): None,
    ("truck", 18): 258,
    ("other-vehicle", 20): 259,
    ("person", 30): 254,
    ("bicyclist", 31): 253,
    ("motorcyclist", 32): 255,
}
"""SemanticKITTI's thing classes, as (name, export id) → the moving raw id its ``.label`` files use
(252 moving-car ... 259 moving-other-vehicle; bicycles and motorcycles have none: a ridden one is the
bicyclist's or motorcyclist's). A class entry that says neither ``thing`` nor ``moving_id`` and matches
one of these by name and export id is that thing, so schemas written before classes had the two keys
read as SemanticKITTI defines them; every other class of such a schema is stuff."""


class _Invalid(Exception):
    """Internal: a validation problem without its location; callers prefix file and entry. A cross-class
    problem also says which class and field it is about (``at``) and the problem alone (``problem``), for
    :func:`read_class_list`'s field-named messages."""

    def __init__(self, message: str, *, at: tuple[int, str] | None = None, problem: str = "") -> None:
        super().__init__(message)
        self.at = at
        self.problem = problem or message


# ------------------------------------------------------------------------------------------ classes
@dataclass(frozen=True)
class ClassDef:
    """One class of a schema. Values are checked and normalised (lists become tuples) on construction.

    Raises:
        SchemaError: naming the class, when a field is invalid.
    """

    name: str
    """Unique, non-empty class name (``car``, ``traffic-sign``)."""
    color: tuple[int, int, int]
    """Display colour, RGB 0..255."""
    prompts: tuple[str, ...]
    """Text prompts for the detector (the class's prompt expansion); at least one."""
    export_id: int
    """Raw semantic id written to exported ``.label`` files (1..65535, unique per schema)."""
    gt_ids: tuple[int, ...] = ()
    """Raw ground-truth semantic ids that count as this class (``learning_map`` semantics)."""
    category: str = "other"
    """Coarse group for category mIoU (see :data:`CATEGORIES`)."""
    negative_prompts: tuple[str, ...] = ()
    """Optional prompts describing what this class is NOT."""
    thing: bool | None = None
    """A countable object (car, person): its points form segments and tracks with instance ids; False is
    stuff (road, vegetation). None (not given) takes :data:`SEMANTICKITTI_THINGS`' answer, else False."""
    moving_id: int | None = None
    """Raw id exported for the class's points while its track moves (SemanticKITTI 252-259), or None:
    moving points keep ``export_id``. Only a thing has one; it differs from every class's export id."""

    def __post_init__(self) -> None:
        try:
            fields = _normalise_class(
                name=self.name,
                color=self.color,
                prompts=self.prompts,
                export_id=self.export_id,
                gt_ids=self.gt_ids,
                category=self.category,
                negative_prompts=self.negative_prompts,
                thing=self.thing,
                moving_id=self.moving_id,
            )
        except _Invalid as exc:
            raise SchemaError(f"class {_entry_label(self.name)}: {exc}") from None
        for key, value in fields.items():
            object.__setattr__(self, key, value)

    def to_dict(self) -> dict[str, Any]:
        """Plain YAML/JSON-ready mapping (lists, not tuples)."""
        return {
            "name": self.name,
            "color": list(self.color),
            "export_id": self.export_id,
            "gt_ids": list(self.gt_ids),
            "category": self.category,
            "prompts": list(self.prompts),
            "negative_prompts": list(self.negative_prompts),
            "thing": bool(self.thing),
            "moving_id": self.moving_id,
        }


def _entry_label(name: object) -> str:
    return repr(name) if isinstance(name, str) and name.strip() else "<unnamed>"


def _is_int(value: object) -> TypeGuard[numbers.Integral]:
    # bool is an Integral in Python; `export_id: yes` in YAML must not pass as 1.
    return isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_))


def _text(value: object, what: str) -> str:
    if not isinstance(value, str) or not value.strip():
        raise _Invalid(f"{what} must be a non-empty string (quote words such as yes/no/on/off in YAML)")
    return value.strip()


def _prompt_list(value: object, what: str, *, required: bool) -> tuple[str, ...]:
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, Iterable) or isinstance(value, Mapping):
        raise _Invalid(f"{what} must be a list of strings")
    out: list[str] = []
    seen: set[str] = set()
    for i, item in enumerate(value):
        text = _text(item, f"{what}[{i}]")
        bad = [c for c in _PHRASE_SEPARATORS if c in text]
        if bad:
            raise _Invalid(
                f"{what}[{i}] {text!r} contains {bad[0]!r}, which the detector uses to separate phrases"
            )
        key = text.lower()
        if key in seen:
            raise _Invalid(f"{what}[{i}] {text!r} is listed twice")
        seen.add(key)
        out.append(text)
    if required and not out:
        raise _Invalid(f"{what} must list at least one prompt")
    return tuple(out)


def _color(value: object) -> tuple[int, int, int]:
    problem = "color must be 3 integers 0..255 (RGB) or a '#rrggbb' string"
    if isinstance(value, str):
        match = _HEX_COLOR.match(value.strip())
        if not match:
            raise _Invalid(problem)
        h = match.group(1)
        return (int(h[0:2], 16), int(h[2:4], 16), int(h[4:6], 16))
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if not isinstance(value, Sequence) or len(value) != 3:
        raise _Invalid(problem)
    if not all(_is_int(v) and 0 <= int(v) <= 255 for v in value):
        raise _Invalid(problem)
    r, g, b = (int(v) for v in value)
    return (r, g, b)


def class_name_problem(name: str) -> str | None:
    """Why ``name`` cannot be a class name, or None.

    A class name is one URL path segment in the app (``/classes/{name}``) and a file-name-safe label in
    exports: ``/`` or ``\\`` would split it, and a name of only dots (``.``, ``..``) is removed by every URL
    normaliser, so such a class could not be reached.
    """
    if "/" in name or "\\" in name:
        return "class names may not contain '/' or '\\'"
    if name and set(name) == {"."}:
        return "class names may not consist of dots only"
    return None


def _normalise_entry(entry: Mapping[str, Any]) -> dict[str, Any]:
    """:func:`_normalise_class` of a class entry read from a file: the required keys (present, checked by
    the caller) and the optional ones at their defaults."""
    return _normalise_class(
        name=entry["name"],
        color=entry["color"],
        prompts=entry["prompts"],
        export_id=entry["export_id"],
        gt_ids=entry.get("gt_ids", ()),
        category=entry.get("category", "other"),
        negative_prompts=entry.get("negative_prompts", ()),
        thing=entry.get("thing"),
        moving_id=entry.get("moving_id"),
    )


def _normalise_class(  # noqa: PLR0913  # keyword-only: a class's fields
    *,
    name: object,
    color: object,
    prompts: object,
    export_id: object,
    gt_ids: object,
    category: object,
    negative_prompts: object,
    thing: object = None,
    moving_id: object = None,
) -> dict[str, Any]:
    """Check one class's fields and return them normalised (tuples, plain ints, stripped strings)."""
    out: dict[str, Any] = {"name": _text(name, "name")}
    problem = class_name_problem(out["name"])
    if problem is not None:
        raise _Invalid(f"name: {problem}")
    out["color"] = _color(color)
    out["prompts"] = _prompt_list(prompts, "prompts", required=True)
    if not _is_int(export_id) or not 1 <= int(export_id) <= MAX_RAW_ID:
        raise _Invalid(
            f"export_id must be an integer 1..{MAX_RAW_ID} (0 means unlabeled in exports), got {export_id!r}"
        )
    out["export_id"] = int(export_id)
    if gt_ids is None:
        gt_ids = ()
    if isinstance(gt_ids, np.ndarray):
        gt_ids = gt_ids.tolist()
    if isinstance(gt_ids, (str, Mapping)) or not isinstance(gt_ids, Iterable):
        raise _Invalid("gt_ids must be a list of integers")
    ids: list[int] = []
    for i, gid in enumerate(gt_ids):
        if not _is_int(gid) or not 0 <= int(gid) <= MAX_RAW_ID:
            raise _Invalid(f"gt_ids[{i}] must be an integer 0..{MAX_RAW_ID}, got {gid!r}")
        if int(gid) in ids:
            raise _Invalid(f"gt_ids[{i}] {int(gid)} is listed twice")
        ids.append(int(gid))
    out["gt_ids"] = tuple(ids)
    out["category"] = _text(category, "category")
    negatives = _prompt_list(
        () if negative_prompts is None else negative_prompts, "negative_prompts", required=False
    )
    positives = {p.lower() for p in out["prompts"]}
    for i, neg in enumerate(negatives):
        if neg.lower() in positives:
            raise _Invalid(f"negative_prompts[{i}] {neg!r} is also one of this class's prompts")
    out["negative_prompts"] = negatives
    out["thing"], out["moving_id"] = _thing_fields(out["name"], out["export_id"], thing, moving_id)
    return out


def object_fields(entry: Mapping[str, Any]) -> tuple[bool, int | None]:
    """A stored class entry's ``(thing, moving_id)`` as a schema reads it: an entry written before classes
    had the two keys is :data:`SEMANTICKITTI_THINGS`' entry for its name and export id, else stuff; a
    moving id alone makes a thing. Unchecked (the entry was checked when it was stored)."""
    thing, moving_id = entry.get("thing"), entry.get("moving_id")
    if thing is None and moving_id is None:
        key = (entry.get("name"), entry.get("export_id"))
        return key in SEMANTICKITTI_THINGS, SEMANTICKITTI_THINGS.get(key)  # type: ignore[arg-type]
    return (True if thing is None else bool(thing)), (None if moving_id is None else int(moving_id))


def _thing_fields(name: str, export_id: int, thing: object, moving_id: object) -> tuple[bool, int | None]:
    """``(thing, moving_id)`` checked; both unset → :data:`SEMANTICKITTI_THINGS`' entry or stuff."""
    if thing is None and moving_id is None:
        return object_fields({"name": name, "export_id": export_id})
    if thing is None:
        thing = True
    if not isinstance(thing, (bool, np.bool_)):
        raise _Invalid(f"thing must be true or false, got {thing!r}")
    if moving_id is None:
        return bool(thing), None
    if not _is_int(moving_id) or not 1 <= int(moving_id) <= MAX_RAW_ID:
        raise _Invalid(f"moving_id must be an integer 1..{MAX_RAW_ID} or null, got {moving_id!r}")
    if not thing:
        raise _Invalid("moving_id is set but thing is false: only a thing (a tracked object) moves")
    if int(moving_id) == export_id:
        raise _Invalid(f"moving_id {int(moving_id)} equals export_id: moving points must be told apart")
    return True, int(moving_id)


def _check_classes(classes: Sequence[ClassDef]) -> None:
    """Cross-class rules: non-empty; unique names, export ids, gt ids and prompts."""
    if not classes:
        raise _Invalid("classes: the class list is empty")
    names: dict[str, int] = {}
    exports: dict[int, tuple[int, str]] = {}
    gts: dict[int, int] = {}
    prompts: dict[str, int] = {}

    def where(i: int) -> str:
        return f"classes[{i}] {classes[i].name!r}"

    for i, c in enumerate(classes):
        if not isinstance(c, ClassDef):
            raise _Invalid(f"classes[{i}]: expected a ClassDef, got {type(c).__name__}")
        if c.name in names:
            problem = f"duplicate name (also {where(names[c.name])})"
            raise _Invalid(f"{where(i)}: {problem}", at=(i, "name"), problem=problem)
        names[c.name] = i
        if c.export_id in exports:
            j, kind = exports[c.export_id]
            problem = f"export_id {c.export_id} is already the {kind} of {where(j)}"
            raise _Invalid(f"{where(i)}: {problem}", at=(i, "export_id"), problem=problem)
        exports[c.export_id] = (i, "export_id")
        if c.moving_id is not None:
            # A moving id is written to .label files too: it must name one class only.
            if c.moving_id in exports:
                j, kind = exports[c.moving_id]
                problem = f"moving_id {c.moving_id} is already the {kind} of {where(j)}"
                raise _Invalid(f"{where(i)}: {problem}", at=(i, "moving_id"), problem=problem)
            exports[c.moving_id] = (i, "moving_id")
        for gid in c.gt_ids:
            if gid in gts:
                problem = f"gt id {gid} is already mapped to {where(gts[gid])}"
                raise _Invalid(f"{where(i)}: {problem}", at=(i, "gt_ids"), problem=problem)
            gts[gid] = i
        for p in c.prompts:
            # The class score is a max over prompt tokens; one prompt in two classes ties them everywhere.
            if p.lower() in prompts:
                problem = f"prompt {p!r} is also a prompt of {where(prompts[p.lower()])}"
                raise _Invalid(f"{where(i)}: {problem}", at=(i, "prompts"), problem=problem)
            prompts[p.lower()] = i


# ------------------------------------------------------------------------------------------- schema
@dataclass(frozen=True)
class Schema:
    """An ordered list of classes; class index ``i`` is ``classes[i]``.

    Raises:
        SchemaError: naming the schema and entry, when the class list breaks a rule (empty, duplicate
            names / export ids / prompts, a ground-truth id mapped to two classes).
    """

    name: str
    """Schema name (the file stem for project files)."""
    classes: tuple[ClassDef, ...]
    """The classes in index order."""
    description: str = ""
    """Free text shown in the app."""

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name.strip():
            raise SchemaError(f"schema name must be a non-empty string, got {self.name!r}")
        if not isinstance(self.description, str):
            raise SchemaError(f"schema {self.name!r}: description must be a string")
        if isinstance(self.classes, (str, Mapping)) or not isinstance(self.classes, Iterable):
            raise SchemaError(f"schema {self.name!r}: classes must be a sequence of ClassDef")
        classes = tuple(self.classes)
        try:
            _check_classes(classes)
        except _Invalid as exc:
            raise SchemaError(f"schema {self.name!r}: {exc}") from None
        object.__setattr__(self, "classes", classes)

    @property
    def num_classes(self) -> int:
        return len(self.classes)

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.classes]

    def index(self, name: str) -> int:
        """Class index of ``name``.

        Raises:
            SchemaError: naming the unknown class and listing the known ones.
        """
        for i, c in enumerate(self.classes):
            if c.name == name:
                return i
        raise SchemaError(f"schema {self.name!r}: unknown class {name!r} (classes: {', '.join(self.names)})")

    def colors(self) -> npt.NDArray[np.uint8]:
        """(C, 3) uint8 RGB colours."""
        return np.array([c.color for c in self.classes], dtype=np.uint8).reshape(-1, 3)

    def export_ids(self) -> npt.NDArray[np.uint32]:
        """(C,) uint32 raw ids written to ``.label`` files for class indices 0..C-1."""
        return np.array([c.export_id for c in self.classes], dtype=np.uint32)

    def things(self) -> npt.NDArray[np.bool_]:
        """(C,) bool: which classes are things (tracked objects with instance ids)."""
        return np.array([bool(c.thing) for c in self.classes], dtype=bool)

    def moving_export_ids(self) -> npt.NDArray[np.uint32]:
        """(C,) uint32 raw id written for a class's moving points: its ``moving_id``, else ``export_id``."""
        ids = [c.export_id if c.moving_id is None else c.moving_id for c in self.classes]
        return np.array(ids, dtype=np.uint32)

    def categories(self) -> list[str]:
        """Category of each class, in class order."""
        return [c.category for c in self.classes]

    def gt_lut(self) -> npt.NDArray[np.int16]:
        """(65536,) int16 lookup: raw semantic id -> class index, ``UNLABELED`` (-1) where unmapped."""
        lut = np.full(MAX_RAW_ID + 1, UNLABELED, dtype=np.int16)
        for i, c in enumerate(self.classes):
            lut[list(c.gt_ids)] = i
        return lut

    def map_gt(self, raw_labels: npt.ArrayLike) -> npt.NDArray[np.int16]:
        """Class indices of raw ``.label`` values: ``lut[raw & 0xFFFF]`` (the instance bits are dropped).

        Args:
            raw_labels: (N,) integer array, typically uint32 ``semantic | instance << 16``.

        Returns:
            (N,) int16 class indices, ``UNLABELED`` where the semantic id maps to no class.
        """
        raw = np.asarray(raw_labels)
        if not np.issubdtype(raw.dtype, np.integer):
            raise TypeError(f"raw labels must be an integer array, got dtype {raw.dtype}")
        classes: npt.NDArray[np.int16] = self.gt_lut()[raw & MAX_RAW_ID]
        return classes

    def to_dict(self) -> dict[str, Any]:
        """Plain mapping in the file format (see the module docstring)."""
        return {
            "name": self.name,
            "description": self.description,
            "classes": [c.to_dict() for c in self.classes],
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], source: str = "<dict>") -> Schema:
        """Build and validate a schema from a mapping in the file format.

        Args:
            d: mapping with ``name``, ``classes`` and optionally ``description``.
            source: where ``d`` came from (a file path); every error message starts with it.

        Raises:
            SchemaError: ``"<source>: classes[i] '<name>': <problem>"``; its ``field`` is
            ``("classes", "i", key)`` where the problem is one field of one class (``("classes", "i")``
            when it is the entry as a whole).
        """
        if not isinstance(d, Mapping):
            raise SchemaError(f"{source}: expected a mapping with keys {', '.join(_TOP_KEYS)}")
        _reject_unknown(d, _TOP_KEYS, source, "")
        name = d.get("name")
        if not isinstance(name, str) or not name.strip():
            raise SchemaError(f"{source}: name must be a non-empty string")
        description = d.get("description", "")
        if description is None:
            description = ""
        if not isinstance(description, str):
            raise SchemaError(f"{source}: description must be a string")
        raw_classes = d.get("classes")
        if raw_classes is None or raw_classes == []:
            raise SchemaError(f"{source}: classes: the class list is empty")
        if not isinstance(raw_classes, list):
            raise SchemaError(f"{source}: classes must be a list of class entries")
        classes = [_class_from_mapping(entry, source, i) for i, entry in enumerate(raw_classes)]
        try:
            _check_classes(classes)
        except _Invalid as exc:
            at = ("classes", str(exc.at[0]), exc.at[1]) if exc.at else ("classes",)
            raise SchemaError(f"{source}: {exc}", field=at) from None
        return cls(name=name.strip(), classes=tuple(classes), description=description)

    def with_classes(self, classes: Iterable[ClassDef]) -> Schema:
        """A validated copy with another class list (same name and description)."""
        return dataclasses.replace(self, classes=tuple(classes))


def _reject_unknown(d: Mapping[str, Any], allowed: Sequence[str], source: str, where: str) -> None:
    for key in d:
        if key not in allowed:
            close = difflib.get_close_matches(str(key), allowed, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else f" (allowed: {', '.join(allowed)})"
            raise SchemaError(f"{source}: {where}unknown key {key!r}{hint}")


def _class_from_mapping(entry: object, source: str, i: int) -> ClassDef:
    where = f"classes[{i}]"
    if not isinstance(entry, Mapping):
        raise SchemaError(f"{source}: {where}: must be a mapping with keys {', '.join(_REQUIRED_CLASS_KEYS)}")
    name = entry.get("name")
    if isinstance(name, str) and name.strip():
        where += f" {name.strip()!r}"
    _reject_unknown(entry, _CLASS_KEYS, source, f"{where}: ")
    for key in _REQUIRED_CLASS_KEYS:
        if key not in entry:
            raise SchemaError(f"{source}: {where}: missing required key {key!r}")
    try:
        fields = _normalise_entry(entry)
    except _Invalid as exc:
        m = _CLASS_FIELD.match(str(exc))
        at = ("classes", str(i), m.group(1)) if m else ("classes", str(i))
        raise SchemaError(f"{source}: {where}: {exc}", field=at) from None
    return ClassDef(**fields)


# --------------------------------------------------------------------------------------------- files
class _UniqueKeyLoader(yaml.SafeLoader):
    """SafeLoader that refuses duplicate mapping keys (PyYAML silently keeps the last one)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: set[Any] = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"duplicate key {key!r}", key_node.start_mark
                )
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


def _read_yaml(path: Path) -> Any:
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        detail = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise SchemaError(f"{path}: cannot read schema file ({detail})") from exc
    return _parse_yaml(text, str(path))


def _yaml_problem(exc: yaml.YAMLError) -> str:
    mark = getattr(exc, "problem_mark", None)
    problem = " ".join(str(getattr(exc, "problem", None) or exc).split())
    at = f" at line {mark.line + 1}" if mark is not None else ""
    return f"invalid YAML{at}: {problem}"


def _parse_yaml(text: str, source: str) -> Any:
    try:
        return yaml.load(text, Loader=_UniqueKeyLoader)  # safe: a SafeLoader subclass
    except yaml.YAMLError as exc:
        raise SchemaError(f"{source}: {_yaml_problem(exc)}") from None


def load_project_file(path: str | Path) -> tuple[Schema, dict[str, Any]]:
    """Read a project file: its schema and its optional top-level ``pipeline:`` mapping.

    A missing ``name`` defaults to the file stem.

    Returns:
        ``(schema, pipeline)`` where ``pipeline`` is the raw mapping of config overrides ({} if absent).

    Raises:
        SchemaError: naming the file and the entry.
    """
    path = Path(path)
    data = _read_yaml(path)
    if data is None:
        raise SchemaError(f"{path}: file is empty (expected keys {', '.join(_TOP_KEYS)})")
    if not isinstance(data, dict):
        raise SchemaError(f"{path}: top level must be a mapping with keys {', '.join(_TOP_KEYS)}")
    _reject_unknown(data, _PROJECT_KEYS, str(path), "")
    data = dict(data)
    pipeline = data.pop("pipeline", None)
    if pipeline is None:
        pipeline = {}
    if not isinstance(pipeline, dict):
        raise SchemaError(f"{path}: pipeline must be a mapping of config overrides")
    data.setdefault("name", path.stem)
    return Schema.from_dict(data, source=str(path)), pipeline


def load_schema(path: str | Path) -> Schema:
    """Read a schema YAML file (a ``pipeline:`` section, if any, is ignored here)."""
    return load_project_file(path)[0]


class _FlowListDumper(yaml.SafeDumper):
    """Writes lists of scalars on one line (``color: [100, 150, 245]``) and everything else in block style."""


def _represent_list(dumper: yaml.SafeDumper, data: list[Any]) -> yaml.Node:
    flow = all(not isinstance(v, (list, dict, tuple)) for v in data)
    return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=flow)


_FlowListDumper.add_representer(list, _represent_list)


def save_schema(schema: Schema, path: str | Path, pipeline: Mapping[str, Any] | None = None) -> None:
    """Write ``schema`` (and an optional ``pipeline:`` mapping) as YAML, atomically.

    The result loads back equal with :func:`load_project_file`.
    """
    doc = schema.to_dict()
    if pipeline is not None:
        if not isinstance(pipeline, Mapping):
            raise SchemaError(f"{path}: pipeline must be a mapping of config overrides")
        doc["pipeline"] = dict(pipeline)
    body = yaml.dump(doc, Dumper=_FlowListDumper, sort_keys=False, allow_unicode=True, width=110)
    header = "# LeAP Studio class schema (written by leap_core.schema.save_schema; edit freely).\n"
    atomic_write_bytes(path, (header + body).encode("utf-8"))


# -------------------------------------------------------------------------------------- class lists
MAX_CLASS_LIST_BYTES = 256 * 1024
"""Largest class-list file :func:`read_class_list` reads (the 19 SemanticKITTI classes take about 4 KiB)."""

_CLASS_FIELD = re.compile(r"^(" + "|".join(_CLASS_KEYS) + r")(\[\d+\])?:?\s+(.*)$", re.DOTALL)


class ClassListError(SchemaError):
    """A class-list file (:func:`read_class_list`) is invalid: ``where`` is the field at fault in the
    file's terms (``classes[3].prompts``, ``classes``, or ``""`` for the file as a whole) and ``problem``
    says what is wrong with it; the message is ``"<where>: <problem>"``."""

    def __init__(self, where: str, problem: str) -> None:
        self.where = where
        self.problem = problem
        super().__init__(f"{where}: {problem}" if where else problem, field=(where,) if where else ())


def read_class_list(text: str, default_name: str = "uploaded") -> Schema:
    """A class list written as a project file's ``classes:`` part (what :func:`class_list_yaml` writes):
    a mapping with ``classes`` and optionally ``name`` and ``description``, or the bare list of classes.

    Unlike :func:`load_project_file` (whose messages name the file for the command line) every problem
    names the field in the file, for people who fix the file in an editor, e.g.
    ``classes[3].prompts: must list at least one prompt``.

    Raises:
        ClassListError: the first problem found.
    """
    if len(text.encode("utf-8")) > MAX_CLASS_LIST_BYTES:
        raise ClassListError("", f"the file is larger than {MAX_CLASS_LIST_BYTES // 1024} KiB")
    try:
        data = yaml.load(text, Loader=_UniqueKeyLoader)  # safe: a SafeLoader subclass
    except yaml.YAMLError as exc:
        raise ClassListError("", _yaml_problem(exc)) from None
    if isinstance(data, list):
        data = {"classes": data}
    if not isinstance(data, dict):
        raise ClassListError("", "expected a mapping with a 'classes:' list (the classes part of a preset)")
    for key in data:
        if key == "pipeline":
            raise ClassListError(
                "pipeline", "a class list holds classes only; set the pipeline in the project's settings"
            )
        if key not in _TOP_KEYS:
            close = difflib.get_close_matches(str(key), _TOP_KEYS, n=1)
            hint = f"did you mean {close[0]!r}?" if close else f"allowed: {', '.join(_TOP_KEYS)}"
            raise ClassListError(str(key), f"unknown key ({hint})")
    name = data.get("name", default_name)
    if not isinstance(name, str) or not name.strip() or len(name.strip()) > 64:
        raise ClassListError("name", "must be text of 1 to 64 characters")
    description = data.get("description") or ""
    if not isinstance(description, str):
        raise ClassListError("description", "must be text")
    raw = data.get("classes")
    if not isinstance(raw, list) or not raw:
        raise ClassListError("classes", "must be a list of at least one class")
    classes = [_class_from_entry(entry, i) for i, entry in enumerate(raw)]
    try:
        _check_classes(classes)
    except _Invalid as exc:
        where = f"classes[{exc.at[0]}].{exc.at[1]}" if exc.at else "classes"
        raise ClassListError(where, exc.problem) from None
    return Schema(name=name.strip(), classes=tuple(classes), description=description)


def _class_from_entry(entry: object, i: int) -> ClassDef:
    where = f"classes[{i}]"
    if not isinstance(entry, Mapping):
        raise ClassListError(where, f"must be a mapping with keys {', '.join(_REQUIRED_CLASS_KEYS)}")
    for key in entry:
        if key not in _CLASS_KEYS:
            close = difflib.get_close_matches(str(key), _CLASS_KEYS, n=1)
            hint = f"did you mean {close[0]!r}?" if close else f"allowed: {', '.join(_CLASS_KEYS)}"
            raise ClassListError(f"{where}.{key}", f"unknown key ({hint})")
    for key in _REQUIRED_CLASS_KEYS:
        if key not in entry:
            raise ClassListError(
                f"{where}.{key}", f"missing (every class needs {', '.join(_REQUIRED_CLASS_KEYS)})"
            )
    try:
        fields = _normalise_entry(entry)
    except _Invalid as exc:
        # Each field's messages start with the field ("prompts[1] 'x' is listed twice"): that part goes
        # into the location, so the reader sees the path once and the problem after it.
        m = _CLASS_FIELD.match(str(exc))
        if m is None:
            raise ClassListError(where, str(exc)) from None
        raise ClassListError(f"{where}.{m.group(1)}{m.group(2) or ''}", m.group(3)) from None
    return ClassDef(**fields)


def class_list_yaml(schema: Schema) -> str:
    """``schema`` as a class-list file: what :func:`read_class_list` reads back into the same classes."""
    body = yaml.dump(schema.to_dict(), Dumper=_FlowListDumper, sort_keys=False, allow_unicode=True, width=110)
    return f"# LeAP Studio class list {schema.name!r}: upload it in the create-project form.\n{body}"


def projects_dir() -> Path:
    """The folder of the built-in project files: the repository's ``projects/``, installed as the package
    ``leap_core.projects`` (pyproject.toml's package-dir), so that an editable install reads the
    repository's folder and a regular install its own copy."""
    return Path(str(resources.files("leap_core.projects")))


def builtin_names() -> list[str]:
    """Names of the built-in project files (``projects/<name>.yaml``), sorted."""
    folder = projects_dir()
    return sorted(p.stem for p in folder.glob("*.yaml")) if folder.is_dir() else []


def builtin_path(name: str) -> Path:
    """The file of the built-in project ``name``: ``projects/<name>.yaml``; a name is never a path.

    Raises:
        SchemaError: for an unknown name, listing the available ones.
    """
    folder = projects_dir()
    path = folder / f"{name}.yaml"
    if not isinstance(name, str) or not _SCHEMA_NAME.match(name) or not path.is_file():
        raise SchemaError(
            f"unknown built-in schema {name!r}: no {folder / (str(name) + '.yaml')} "
            f"(available: {', '.join(builtin_names()) or 'none'})"
        )
    return path


def builtin_schema(name: str = "semantickitti") -> Schema:
    """Load the built-in schema ``projects/<name>.yaml`` (its ``pipeline:`` section is
    :func:`leap_core.presets.load_preset`'s business).

    Raises:
        SchemaError: for an unknown name, listing the available ones.
    """
    return load_schema(builtin_path(name))


__all__ = [
    "CATEGORIES",
    "MAX_CLASS_LIST_BYTES",
    "SEMANTICKITTI_THINGS",
    "ClassDef",
    "ClassListError",
    "Schema",
    "builtin_names",
    "builtin_path",
    "builtin_schema",
    "class_list_yaml",
    "class_name_problem",
    "load_project_file",
    "load_schema",
    "object_fields",
    "projects_dir",
    "read_class_list",
    "save_schema",
]
