"""The ``paper`` preset of the lab's simulated-paper labeler, written by lab/fit_labeler.py.

Fitted on the demo (`leap synth data/demo --frames 60 --seed 0`, every frame; warm from the former preset,
which was fitted on tuning sequences 21-28) (the preset is defined by the demo's point row: python -m
lab.fit_labeler): the point row (camera view, the paper's merged classes) of these settings there, each
class's IoU averaged over the sequences that contain it, against the paper's Table 1:

    class          paper  fitted
    car             77.2   77.6
    bicycle         25.5   27.8
    other-vehicle   30.3   29.2
    person          31.9   35.4
    road            87.1   86.6
    sidewalk        46.1   46.5
    other-ground     0.0    0.1
    manmade         64.3   62.8
    vegetation      64.7   67.1
    terrain         72.3   71.7
    mIoU            49.9   50.5   (over the classes above)
"""

from typing import Any

PAPER_PRESET: dict[str, Any] = {
    "seed": 0,
    "recall": 0.9,
    "class_recall": {
        "bicycle": 0.7,
        "motorcycle": 0.7,
        "bicyclist": 0.7,
        "motorcyclist": 0.7,
        "person": 0.8,
        "other-vehicle": 0.8,
        "pole": 0.75,
        "traffic-sign": 0.75,
        "trunk": 0.75,
        "other-ground": 0.6,
    },
    "min_region_px": 16,
    "confusion_prob": 0.0,
    "persistence_frames": 5,
    "confusion_pairs": (
        ("car", "truck"),
        ("car", "other-vehicle"),
        ("bicycle", "person"),
        ("bicyclist", "person"),
        ("motorcycle", "bicycle"),
        ("road", "sidewalk"),
        ("road", "parking"),
        ("sidewalk", "terrain"),
        ("other-ground", "sidewalk"),
        ("terrain", "vegetation"),
        ("fence", "vegetation"),
        ("building", "fence"),
        ("pole", "trunk"),
        ("pole", "traffic-sign"),
        ("vegetation", "trunk"),
    ),
    "peak_prob": (0.5, 0.9),
    "partner_share": 0.5,
    "dirichlet_alpha": 1.0,
    "confidence": (0.3, 0.9),
    "bleed_px": 3,
    "stuff_bleed_px": 1,
    "jitter_px": 1.0,
    "jitter_deg": 0.1,
    "match_detection": {
        "exact": 1.0,
        "synonym": 0.95,
        "descriptive": 0.85,
        "hypernym": 0.5,
    },
    "match_confidence": {
        "exact": 1.0,
        "synonym": 0.85,
        "descriptive": 0.7,
        "hypernym": 0.45,
    },
    "match_temperature": 0.1,
    "instance_miss": 0.1,
    "instance_merge": 0.1,
    "instance_split": 0.05,
    "class_confusion": {
        "bicycle": 0.592,
        "bicyclist": 0.592,
        "building": 0.12,
        "fence": 0.12,
        "other-ground": 1.0,
        "other-vehicle": 0.656,
        "parking": 0.011,
        "person": 0.1,
        "pole": 0.12,
        "road": 0.011,
        "sidewalk": 0.417,
        "terrain": 0.024,
        "traffic-sign": 0.12,
        "truck": 0.656,
        "trunk": 0.761,
        "vegetation": 0.761,
    },
    "confusion_targets": {
        "car": {
            "truck": 1.0,
            "other-vehicle": 1.0,
        },
        "truck": {
            "car": 1.0,
            "building": 3.0,
        },
        "other-vehicle": {
            "car": 1.0,
            "building": 3.0,
        },
        "bicycle": {
            "person": 1.0,
            "pole": 1.0,
            "fence": 1.0,
        },
        "bicyclist": {
            "person": 1.0,
        },
        "motorcycle": {
            "bicycle": 1.0,
        },
        "motorcyclist": {
            "person": 1.0,
        },
        "person": {
            "bicyclist": 0.5,
            "pole": 1.0,
            "car": 1.0,
        },
        "road": {
            "sidewalk": 2.0,
            "parking": 1.0,
        },
        "parking": {
            "road": 1.0,
            "sidewalk": 1.0,
        },
        "sidewalk": {
            "road": 2.0,
            "other-ground": 1.0,
            "building": 1.0,
        },
        "other-ground": {
            "sidewalk": 2.0,
            "road": 1.0,
        },
        "building": {
            "road": 1.0,
            "sidewalk": 2.0,
            "vegetation": 0.1,
            "fence": 1.0,
        },
        "fence": {
            "vegetation": 1.0,
            "sidewalk": 1.0,
            "building": 1.0,
        },
        "pole": {
            "trunk": 1.0,
            "traffic-sign": 1.0,
            "building": 1.0,
        },
        "traffic-sign": {
            "pole": 1.0,
            "building": 1.0,
        },
        "vegetation": {
            "building": 2.0,
            "trunk": 1.0,
        },
        "trunk": {
            "vegetation": 1.0,
            "pole": 1.0,
        },
        "terrain": {
            "vegetation": 1.0,
            "sidewalk": 1.0,
        },
    },
    "small_region_px": 150,
    "box_leak_prob": 0.1,
    "class_box_leak": {
        "car": 0.125,
        "person": 0.936,
    },
    "box_leak_margin": 0.3,
    "pair_merge_prob": 0.3,
    "pair_merge_gap_px": 4,
    "stuff_grow_prob": 0.0,
    "stuff_grow_px": 6,
    "stuff_tile_px": 32,
    "stuff_world_tile": 1,
    "stratified_draws": True,
    "drift_draws": True,
}
