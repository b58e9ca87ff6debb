"""Class schemas: the built-in SemanticKITTI schema, ground-truth mapping, YAML round trips, validation."""

from __future__ import annotations

import copy
import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from leap_core.errors import SchemaError
from leap_core.schema import (
    ClassDef,
    Schema,
    builtin_schema,
    load_project_file,
    load_schema,
    projects_dir,
    save_schema,
)
from leap_core.types import UNLABELED

SEMANTICKITTI_19 = [
    ("car", 10), ("bicycle", 11), ("motorcycle", 15), ("truck", 18), ("other-vehicle", 20),
    ("person", 30), ("bicyclist", 31), ("motorcyclist", 32), ("road", 40), ("parking", 44),
    ("sidewalk", 48), ("other-ground", 49), ("building", 50), ("fence", 51), ("vegetation", 70),
    ("trunk", 71), ("terrain", 72), ("pole", 80), ("traffic-sign", 81),
]  # fmt: skip

# SemanticKITTI's learning_map (semantic-kitti.yaml), written as raw id -> class name (None = ignored).
LEARNING_MAP: dict[int, str | None] = {
    0: None, 1: None, 10: "car", 11: "bicycle", 13: "other-vehicle", 15: "motorcycle",
    16: "other-vehicle", 18: "truck", 20: "other-vehicle", 30: "person", 31: "bicyclist",
    32: "motorcyclist", 40: "road", 44: "parking", 48: "sidewalk", 49: "other-ground",
    50: "building", 51: "fence", 52: None, 60: "road", 70: "vegetation", 71: "trunk",
    72: "terrain", 80: "pole", 81: "traffic-sign", 99: None, 252: "car", 253: "bicyclist",
    254: "person", 255: "motorcyclist", 256: "other-vehicle", 257: "other-vehicle", 258: "truck",
    259: "other-vehicle",
}  # fmt: skip

# RGB colours given in the paper (docs/METHOD.md E.7) and SemanticKITTI color_map entries (BGR) turned
# into RGB.
PAPER_RGB = {
    "car": (100, 150, 245), "road": (255, 0, 255), "sidewalk": (75, 0, 75), "building": (255, 200, 0),
    "vegetation": (0, 175, 0), "terrain": (150, 240, 80), "pole": (255, 240, 150),
    "traffic-sign": (255, 0, 0), "person": (255, 30, 30), "fence": (255, 120, 50), "trunk": (135, 60, 0),
}  # fmt: skip
COLOR_MAP_BGR = {
    "bicycle": (245, 230, 100), "motorcycle": (150, 60, 30), "truck": (180, 30, 80),
    "other-vehicle": (255, 0, 0), "bicyclist": (200, 40, 255), "motorcyclist": (90, 30, 150),
    "parking": (255, 150, 255), "other-ground": (75, 0, 175),
}  # fmt: skip

CATEGORY_OF = {
    "vehicle": ["car", "bicycle", "motorcycle", "truck", "other-vehicle"],
    "human": ["person", "bicyclist", "motorcyclist"],
    "flat": ["road", "parking", "sidewalk", "other-ground"],
    "construction": ["building", "fence"],
    "nature": ["vegetation", "trunk", "terrain"],
    "object": ["pole", "traffic-sign"],
}


@pytest.fixture(scope="module")
def kitti() -> Schema:
    return builtin_schema("semantickitti")


def small_schema() -> Schema:
    return Schema(
        name="tiny",
        classes=(
            ClassDef("car", (1, 2, 3), ("car", "automobile"), 10, gt_ids=(10, 252), category="vehicle"),
            ClassDef("road", (4, 5, 6), ("road",), 40, gt_ids=(40,), category="flat"),
        ),
    )


# ---------------------------------------------------------------------------------- built-in schema
def test_builtin_has_the_19_classes_in_order(kitti: Schema) -> None:
    assert kitti.name == "semantickitti"
    assert kitti.num_classes == 19
    assert kitti.names == [n for n, _ in SEMANTICKITTI_19]
    ids = kitti.export_ids()
    assert ids.dtype == np.uint32
    assert ids.tolist() == [i for _, i in SEMANTICKITTI_19]
    assert [kitti.index(n) for n, _ in SEMANTICKITTI_19] == list(range(19))


def test_builtin_colors(kitti: Schema) -> None:
    colors = kitti.colors()
    assert colors.dtype == np.uint8 and colors.shape == (19, 3)
    for name, rgb in PAPER_RGB.items():
        assert tuple(colors[kitti.index(name)]) == rgb, name
    for name, (b, g, r) in COLOR_MAP_BGR.items():
        assert tuple(colors[kitti.index(name)]) == (r, g, b), name


def test_builtin_categories(kitti: Schema) -> None:
    cats = kitti.categories()
    for cat, names in CATEGORY_OF.items():
        assert sorted(n for n, c in zip(kitti.names, cats, strict=True) if c == cat) == sorted(names)


def test_builtin_prompts_follow_the_three_strategies(kitti: Schema) -> None:
    by_name = {c.name: c for c in kitti.classes}
    assert {"car", "automobile", "van"} <= set(by_name["car"].prompts)  # synonym + helper category
    # Descriptive replacement: the vague name is not a prompt, what it means is.
    assert {"bus", "train", "tram", "trailer"} <= set(by_name["other-vehicle"].prompts)
    assert "other-vehicle" not in by_name["other-vehicle"].prompts
    assert all(len(c.prompts) >= 2 for c in kitti.classes)


def test_builtin_prompt_words_are_not_shared_between_classes(kitti: Schema) -> None:
    """The class score is a max over prompt tokens: a word in two classes' prompts ties them."""
    owner: dict[str, str] = {}
    for c in kitti.classes:
        for word in {w for p in c.prompts for w in re.split(r"[\s-]+", p.lower())}:
            assert owner.setdefault(word, c.name) == c.name, f"{word!r} in {owner[word]} and {c.name}"


def test_builtin_file_is_commented_for_people() -> None:
    text = (projects_dir() / "semantickitti.yaml").read_text()
    assert text.count("#") > 40
    assert "pipeline:" not in text


# ----------------------------------------------------------------------------- ground-truth mapping
def test_gt_lut_is_semantickitti_learning_map(kitti: Schema) -> None:
    lut = kitti.gt_lut()
    assert lut.shape == (65536,) and lut.dtype == np.int16
    for raw, name in LEARNING_MAP.items():
        assert lut[raw] == (UNLABELED if name is None else kitti.index(name)), raw
    # Exactly the 30 non-ignored learning_map ids are mapped; everything else is unlabeled.
    assert int((lut >= 0).sum()) == 30


def test_map_gt_drops_instance_bits(kitti: Schema) -> None:
    raw = np.array(
        [65791, (7 << 16) | 10, 0xFFFF0000 | 40, 252, 60, 13, 16, 0, 1, 52, 99, 12345, 0xFFFF0000], np.uint32
    )
    out = kitti.map_gt(raw)
    assert out.dtype == np.int16 and out.shape == raw.shape
    assert 65791 == (1 << 16) | 255
    names = [kitti.names[i] if i >= 0 else None for i in out]
    assert names == [
        "motorcyclist", "car", "road", "car", "road", "other-vehicle", "other-vehicle",
        None, None, None, None, None, None,
    ]  # fmt: skip


def test_map_gt_accepts_signed_ints_and_refuses_floats(kitti: Schema) -> None:
    assert kitti.map_gt(np.array([10, 81], np.int64)).tolist() == [0, 18]
    assert kitti.map_gt(np.zeros(0, np.uint32)).shape == (0,)
    with pytest.raises(TypeError, match="integer"):
        kitti.map_gt(np.array([10.0]))


def test_gt_lut_of_small_schema() -> None:
    schema = small_schema()
    lut = schema.gt_lut()
    assert (lut[[10, 252, 40]] == [0, 0, 1]).all()
    assert (np.delete(lut, [10, 252, 40]) == UNLABELED).all()


# ------------------------------------------------------------------------------------ save and load
def test_save_load_round_trip(tmp_path: Path, kitti: Schema) -> None:
    path = tmp_path / "copy.yaml"
    save_schema(kitti, path)
    assert load_schema(path) == kitti
    text = path.read_text()
    assert "color: [100, 150, 245]" in text  # short lists stay on one line, easy to edit


def test_save_load_round_trip_with_pipeline_and_unicode(tmp_path: Path) -> None:
    schema = Schema(
        name="forest",
        description="UAV: trees and paths",
        classes=(
            ClassDef("tree", "#0a8000", ["tree", "conifer"], 1, category="nature", negative_prompts=["bush"]),
            ClassDef("path", [200, 180, 120], "dirt path", 2, gt_ids=[7, 0], category="flat"),
            ClassDef("sign", (255, 0, 0), ("Wegweiser", "signpost"), 65535),
        ),
    )
    assert schema.classes[0].color == (10, 128, 0)
    assert schema.classes[1].prompts == ("dirt path",)
    pipeline = {"fusion": {"voxel_size": 0.1}, "labeler": {"box_threshold": 0.2}}
    path = tmp_path / "forest.yaml"
    save_schema(schema, path, pipeline=pipeline)
    back, back_pipeline = load_project_file(path)
    assert back == schema
    assert back_pipeline == pipeline
    assert load_schema(path) == schema
    assert load_project_file(projects_dir() / "semantickitti.yaml")[1] == {}


def test_dict_round_trip(kitti: Schema) -> None:
    assert Schema.from_dict(kitti.to_dict()) == kitti


def test_save_is_atomic(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "s.yaml"
    save_schema(small_schema(), path)
    before = path.read_bytes()

    def boom(*args: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError):
        save_schema(builtin_schema(), path)
    monkeypatch.undo()
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["s.yaml"]


def test_name_defaults_to_file_stem(tmp_path: Path) -> None:
    d = small_schema().to_dict()
    del d["name"]
    path = tmp_path / "my_project.yaml"
    path.write_text(yaml.safe_dump(d))
    assert load_schema(path).name == "my_project"


def test_builtin_schema_unknown_name() -> None:
    with pytest.raises(SchemaError, match=r"unknown built-in schema 'nope'.*available: .*semantickitti"):
        builtin_schema("nope")
    with pytest.raises(SchemaError, match="unknown built-in schema"):
        builtin_schema("../projects/semantickitti")


def test_index_of_unknown_class_names_it(kitti: Schema) -> None:
    with pytest.raises(SchemaError, match=r"unknown class 'lamp' \(classes: car, bicycle"):
        kitti.index("lamp")


# ----------------------------------------------------------------------------------------- validation
Mutation = Callable[[dict[str, Any]], None]


def _set(i: int, key: str, value: Any) -> Mutation:
    def mutate(d: dict[str, Any]) -> None:
        d["classes"][i][key] = value

    return mutate


def _drop(i: int, key: str) -> Mutation:
    def mutate(d: dict[str, Any]) -> None:
        del d["classes"][i][key]

    return mutate


def _append_gt(i: int, gid: int) -> Mutation:
    def mutate(d: dict[str, Any]) -> None:
        d["classes"][i]["gt_ids"].append(gid)

    return mutate


def _top(key: str, value: Any) -> Mutation:
    def mutate(d: dict[str, Any]) -> None:
        d[key] = value

    return mutate


BAD_COLOR = "classes[3] 'truck': color must be 3 integers 0..255"
OV = "classes[4] 'other-vehicle'"
BAD_EXPORT = "classes[6] 'bicyclist': export_id must be an integer 1..65535"
CASES: list[tuple[str, Mutation, str]] = [
    ("duplicate name", _set(1, "name", "car"), "classes[1] 'car': duplicate name (also classes[0] 'car')"),
    (
        "duplicate export id",
        _set(2, "export_id", 10),
        "classes[2] 'motorcycle': export_id 10 is already the export_id of classes[0] 'car'",
    ),
    (
        "gt id in two classes",
        _append_gt(8, 252),
        "classes[8] 'road': gt id 252 is already mapped to classes[0] 'car'",
    ),
    ("gt id listed twice", _append_gt(8, 40), "classes[8] 'road': gt_ids[2] 40 is listed twice"),
    ("gt id too big", _set(8, "gt_ids", [65536]), "classes[8] 'road': gt_ids[0] must be an integer 0..65535"),
    ("gt ids not a list", _set(8, "gt_ids", "40"), "classes[8] 'road': gt_ids must be a list of integers"),
    ("color out of range", _set(3, "color", [256, 0, 0]), BAD_COLOR),
    ("color negative", _set(3, "color", [-1, 0, 0]), BAD_COLOR),
    ("color two values", _set(3, "color", [1, 2]), BAD_COLOR),
    ("color float", _set(3, "color", [1.5, 2, 3]), BAD_COLOR),
    ("color bool", _set(3, "color", [True, 0, 0]), BAD_COLOR),
    ("color name", _set(3, "color", "red"), BAD_COLOR),
    ("color bad hex", _set(3, "color", "#12345g"), BAD_COLOR),
    ("name of dots", _set(4, "name", ".."), "classes[4] '..': name: class names may not consist of dots"),
    ("name with slash", _set(4, "name", "a/b"), "classes[4] 'a/b': name: class names may not contain '/'"),
    ("no prompts", _set(4, "prompts", []), f"{OV}: prompts must list at least one prompt"),
    ("blank prompt", _set(4, "prompts", ["bus", "  "]), f"{OV}: prompts[1] must be a non-empty string"),
    ("null prompt", _set(4, "prompts", [None]), f"{OV}: prompts[0] must be a non-empty string"),
    ("prompt with dot", _set(4, "prompts", ["bus. train"]), f"{OV}: prompts[0] 'bus. train' contains '.'"),
    ("prompt twice", _set(4, "prompts", ["bus", "Bus"]), f"{OV}: prompts[1] 'Bus' is listed twice"),
    (
        "prompt in two classes",
        _set(3, "prompts", ["truck", "car"]),
        "classes[3] 'truck': prompt 'car' is also a prompt of classes[0] 'car'",
    ),
    (
        "negative equals positive",
        _set(0, "negative_prompts", ["van"]),
        "classes[0] 'car': negative_prompts[0] 'van' is also one of this class's prompts",
    ),
    (
        "unknown class key",
        _set(3, "colour", [1, 2, 3]),
        "classes[3] 'truck': unknown key 'colour' (did you mean 'color'?)",
    ),
    ("unknown top key", _top("clases", []), "unknown key 'clases' (did you mean 'classes'?)"),
    ("missing key", _drop(5, "export_id"), "classes[5] 'person': missing required key 'export_id'"),
    ("export id too big", _set(6, "export_id", 65536), BAD_EXPORT),
    ("export id zero", _set(6, "export_id", 0), BAD_EXPORT),
    ("export id negative", _set(6, "export_id", -3), BAD_EXPORT),
    ("export id text", _set(6, "export_id", "31"), BAD_EXPORT),
    ("name not text", _set(2, "name", True), "classes[2]: name must be a non-empty string"),
    ("empty name", _set(2, "name", ""), "classes[2]: name must be a non-empty string"),
    ("empty category", _set(2, "category", ""), "classes[2] 'motorcycle': category must be a non-empty"),
    ("entry not a mapping", lambda d: d["classes"].__setitem__(7, "rider"), "classes[7]: must be a mapping"),
    ("empty class list", _top("classes", []), "classes: the class list is empty"),
    ("no class list", lambda d: d.pop("classes"), "classes: the class list is empty"),
    ("classes not a list", _top("classes", {"car": 1}), "classes must be a list"),
    ("pipeline not a mapping", _top("pipeline", [1, 2]), "pipeline must be a mapping"),
    ("description not text", _top("description", ["a"]), "description must be a string"),
]


@pytest.mark.parametrize(("mutate", "expected"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_validation_error_names_file_and_entry(
    tmp_path: Path, kitti: Schema, mutate: Mutation, expected: str
) -> None:
    d = copy.deepcopy(kitti.to_dict())
    mutate(d)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(d, sort_keys=False))
    with pytest.raises(SchemaError) as exc:
        load_schema(path)
    msg = str(exc.value)
    assert msg.startswith(f"{path}: "), msg
    assert expected in msg, msg
    assert "\n" not in msg


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("name: x\nclasses: [\n", "invalid YAML at line"),
        ("name: x\nclasses:\n  - name: car\n    name: auto\n", "at line 4: duplicate key 'name'"),
        ("", "file is empty"),
        ("- a\n- b\n", "top level must be a mapping"),
    ],
)
def test_unreadable_files_name_the_file(tmp_path: Path, text: str, expected: str) -> None:
    path = tmp_path / "broken.yaml"
    path.write_text(text)
    with pytest.raises(SchemaError, match=re.escape(expected)) as exc:
        load_schema(path)
    assert str(exc.value).startswith(f"{path}: ")


def test_missing_file_names_it(tmp_path: Path) -> None:
    with pytest.raises(SchemaError, match="cannot read schema file") as exc:
        load_schema(tmp_path / "gone.yaml")
    assert "gone.yaml" in str(exc.value)


def test_from_dict_uses_the_source_in_messages() -> None:
    with pytest.raises(SchemaError, match=r"^upload\.yaml: name must be a non-empty string$"):
        Schema.from_dict({"classes": []}, source="upload.yaml")
    with pytest.raises(SchemaError, match=r"^<dict>: classes: the class list is empty$"):
        Schema.from_dict({"name": "x", "classes": []})


# ---------------------------------------------------------------------------------- direct building
def test_classdef_normalises_to_tuples_and_plain_ints() -> None:
    c = ClassDef("car", [np.uint8(1), 2, 3], ["car"], np.int64(10), gt_ids=np.array([10, 252]))
    assert c.color == (1, 2, 3) and c.prompts == ("car",) and c.gt_ids == (10, 252)
    assert type(c.export_id) is int and all(type(v) is int for v in c.color + c.gt_ids)
    assert c.category == "other" and c.negative_prompts == ()
    hash(c)  # frozen and hashable once normalised


def test_classdef_errors_name_the_class() -> None:
    with pytest.raises(SchemaError, match=r"^class 'pole': color must be 3 integers"):
        ClassDef("pole", (0, 0, 300), ("pole",), 80)
    with pytest.raises(SchemaError, match=r"^class 'pole': prompts must list at least one prompt"):
        ClassDef("pole", (0, 0, 0), (), 80)


def test_schema_checks_cross_class_rules() -> None:
    car = ClassDef("car", (1, 2, 3), ("car",), 10)
    with pytest.raises(SchemaError, match=r"^schema 's': classes\[1\] 'car': duplicate name"):
        Schema("s", (car, car))
    with pytest.raises(SchemaError, match=r"^schema 's': classes: the class list is empty"):
        Schema("s", ())
    with pytest.raises(SchemaError, match="schema name must be a non-empty string"):
        Schema("", (car,))


def test_with_classes_validates_and_keeps_the_rest() -> None:
    schema = small_schema()
    lamp = ClassDef("lamp", (9, 9, 9), ("street lamp",), 99, gt_ids=(80,), category="object")
    bigger = schema.with_classes([*schema.classes, lamp])
    assert bigger.names == ["car", "road", "lamp"] and bigger.name == "tiny"
    assert bigger.map_gt(np.array([80, 40], np.uint32)).tolist() == [2, 1]
    assert schema.num_classes == 2
    clash = ClassDef("lane", (9, 9, 9), ("lane",), 60, gt_ids=(40,))
    with pytest.raises(SchemaError, match="gt id 40 is already mapped to classes\\[1\\] 'road'"):
        schema.with_classes([*schema.classes, clash])


# ------------------------------------------------------------------------------- things and movers
SEMANTICKITTI_MOVING = {
    "car": 252, "bicyclist": 253, "person": 254, "motorcyclist": 255, "truck": 258, "other-vehicle": 259,
}  # fmt: skip


def test_builtin_things_and_moving_ids(kitti: Schema) -> None:
    things = {c.name for c in kitti.classes if c.thing}
    assert things == {"car", "bicycle", "motorcycle", "truck", "other-vehicle", "person", "bicyclist",
                      "motorcyclist"}  # fmt: skip
    assert {c.name: c.moving_id for c in kitti.classes if c.moving_id} == SEMANTICKITTI_MOVING
    assert kitti.things().tolist() == [c.name in things for c in kitti.classes]
    moving = kitti.moving_export_ids()
    assert moving[kitti.index("person")] == 254 and moving[kitti.index("road")] == 40


def test_older_schema_without_the_keys_gets_semantickitti_things(kitti: Schema) -> None:
    doc = kitti.to_dict()
    for c in doc["classes"]:
        del c["thing"], c["moving_id"]
    old = Schema.from_dict(doc)
    assert old == kitti
    # A class named like a SemanticKITTI thing but with another export id is not guessed to be one.
    assert ClassDef("car", (1, 2, 3), ("car",), 4).thing is False


@pytest.mark.parametrize(
    ("entry", "problem"),
    [
        ({"thing": "yes"}, "thing must be true or false"),
        ({"thing": False, "moving_id": 300}, "only a thing"),
        ({"thing": True, "moving_id": 7}, "equals export_id"),
        ({"thing": True, "moving_id": 70000}, "moving_id must be an integer"),
    ],
)
def test_thing_fields_are_checked(entry: dict[str, Any], problem: str) -> None:
    with pytest.raises(SchemaError, match=problem):
        ClassDef("x", (1, 2, 3), ("x",), 7, **entry)


def test_moving_id_may_not_be_another_class_export_id() -> None:
    a = ClassDef("a", (1, 2, 3), ("a",), 10, thing=True, moving_id=40)
    b = ClassDef("b", (1, 2, 3), ("b",), 40)
    with pytest.raises(SchemaError, match="export_id 40 is already the moving_id of classes\\[0\\] 'a'"):
        Schema("s", (a, b))
