"""Stage 1 — kitchens: the 30 compiled iTHOR kitchens, checked against the raw facts in ../shared."""

from __future__ import annotations

import gzip
import json
from pathlib import Path

import pytest

from kgnavbench import kitchens
from kgnavbench.kitchens import KITCHEN_NAMES, KitchenError, load_kitchen

THOR_DATA = Path(__file__).resolve().parents[2] / "shared" / "thor_data"
EGG = "Egg|-02.04|+00.81|+01.24"
FRIDGE = "Fridge|-02.10|+00.00|+01.07"


@pytest.fixture
def thor_data() -> Path:
    if not THOR_DATA.is_dir():
        pytest.skip(f"{THOR_DATA} is absent (the raw kitchen facts live beside the repository)")
    return THOR_DATA


@pytest.fixture
def fresh_cache():
    load_kitchen.cache_clear()
    yield
    load_kitchen.cache_clear()


def test_all_30_kitchens_load():
    assert tuple(f"FloorPlan{i}" for i in range(1, 31)) == KITCHEN_NAMES
    for name in KITCHEN_NAMES:
        k = load_kitchen(name)
        assert k.name == name
        assert k.grid == 0.25
        assert len(k.reachable) > 20, name
        assert list(k.reachable) == sorted(set(k.reachable)), name
        assert len(k.objects) > 40, name
        assert k.placements, name
        x0, z0, x1, z1 = k.room
        # the walls enclose every cell the agent may stand on
        for x, z in k.reachable_points:
            assert x0 < x < x1 and z0 < z < z1, (name, x, z)


def test_reachable_cells_are_alfreds_layout(thor_data):
    np = pytest.importorskip("numpy")
    for name in KITCHEN_NAMES:
        layout = np.load(thor_data / f"alfred/gen/layouts/{name}-layout.npy")
        cells = {(round(float(x) / 0.25), round(float(z) / 0.25)) for x, z in layout}
        assert len(cells) == len(layout), f"{name}: layout points collapse onto shared cells"
        assert set(load_kitchen(name).reachable) == cells, name


def test_recompiling_floorplan1_gives_the_committed_file(thor_data):
    record = kitchens.compile_kitchen("FloorPlan1", thor_data)
    with gzip.open(kitchens.KITCHEN_DIR / "FloorPlan1.json.gz", "rt") as f:
        committed = json.load(f)
    # through JSON, so tuples and lists compare alike
    assert json.loads(json.dumps(record)) == committed


def test_compile_rejects_a_folder_that_is_not_thor_data(tmp_path):
    with pytest.raises(KitchenError, match="not the thor_data folder"):
        kitchens.compile_kitchen("FloorPlan1", tmp_path)


@pytest.mark.parametrize("name", ["FloorPlan0", "FloorPlan31", "Kitchen1", "floorplan1", ""])
def test_unknown_kitchen_is_named(name):
    with pytest.raises(KitchenError, match=f"unknown kitchen {name!r}"):
        load_kitchen(name)


@pytest.mark.parametrize(
    "content",
    [
        b"this is not gzip at all",
        gzip.compress(b"{not json"),
        gzip.compress(b"[1, 2, 3]"),
        gzip.compress(json.dumps({"format": 999, "name": "FloorPlan1"}).encode()),
        gzip.compress(json.dumps({"format": kitchens.FORMAT_VERSION, "name": "FloorPlan1"}).encode()),
        gzip.compress(b'{"format": 1, "name": "FloorPlan1"')[:-7],  # truncated stream
    ],
    ids=["not-gzip", "not-json", "not-a-record", "wrong-format", "missing-keys", "truncated"],
)
def test_corrupt_kitchen_file_is_reported(tmp_path, monkeypatch, fresh_cache, content):
    (tmp_path / "FloorPlan1.json.gz").write_bytes(content)
    monkeypatch.setattr(kitchens, "KITCHEN_DIR", tmp_path)
    with pytest.raises(KitchenError, match="FloorPlan1.json.gz is corrupt"):
        load_kitchen("FloorPlan1")


def test_missing_kitchen_file_is_reported(tmp_path, monkeypatch, fresh_cache):
    monkeypatch.setattr(kitchens, "KITCHEN_DIR", tmp_path)
    with pytest.raises(KitchenError, match="FloorPlan2.json.gz is missing"):
        load_kitchen("FloorPlan2")


def test_floorplan1_egg_is_hidden_in_the_fridge():
    k = load_kitchen("FloorPlan1")
    egg, fridge = k.object(EGG), k.object(FRIDGE)
    assert egg.type == "Egg" and egg.pickupable
    assert egg.hidden
    assert egg.parent == FRIDGE
    assert fridge.openable and fridge.receptacle and not fridge.hidden
    assert EGG in fridge.contents
    assert fridge.front is not None
    # the Egg sits inside the Fridge's footprint, between its floor and top
    (poly,) = fridge.footprint
    xs, zs = [p[0] for p in poly], [p[1] for p in poly]
    assert min(xs) < egg.center[0] < max(xs) and min(zs) < egg.center[1] < max(zs)
    assert fridge.y_range[0] < egg.y_range[0] < egg.y_range[1] < fridge.y_range[1]


def test_unknown_object_id_is_named():
    k = load_kitchen("FloorPlan1")
    with pytest.raises(KitchenError, match=r"no object 'Egg\|nowhere'"):
        k.object("Egg|nowhere")
    with pytest.raises(KitchenError, match="no object 'Unicorn'"):
        k.index("Unicorn")
    assert k.objects[k.index(EGG)].id == EGG


def test_object_types_vocabulary():
    types = kitchens.object_types()
    assert len(types) == 125
    assert list(types) == sorted(set(types))
    assert {"Egg", "Fridge", "CounterTop", "Cabinet", "Apple"} <= set(types)
    for name in KITCHEN_NAMES:
        assert {o.type for o in load_kitchen(name).objects} <= set(types), name


def test_object_records_are_consistent():
    for name in KITCHEN_NAMES:
        k = load_kitchen(name)
        by_id = {o.id: o for o in k.objects}
        assert len(by_id) == len(k.objects), f"{name}: duplicate object ids"
        for o in k.objects:
            parts = o.id.split("|")  # "Type|x|y|z", or "Sink|x|y|z|SinkBasin" for a sink's basin
            assert o.type in (parts[0], parts[-1]) and len(parts) in (4, 5), (name, o.id)
            assert o.footprint and all(len(poly) >= 3 for poly in o.footprint), (name, o.id)
            # (a few wall cabinets and windows reach up to 2.82 m, above the 2.6 m ceiling)
            assert 0.0 <= o.y_range[0] <= o.y_range[1] <= 3.0, (name, o.id, o.y_range)
            assert o.parent is None or o.parent in by_id, (name, o.id, o.parent)
            assert all(c in by_id for c in o.contents), (name, o.id)
            assert (o.front is not None) == o.openable, (name, o.id)
            # hidden at the start <=> some receptacle up the parent chain is openable (all start closed)
            chain, p = [], o.parent
            while p is not None and p not in chain:
                chain.append(p)
                p = by_id[p].parent
            assert p is None, f"{name}: {o.id} has a parent cycle {chain}"
            assert o.hidden == any(by_id[q].openable for q in chain), (name, o.id)
            if not o.pickupable:
                # fixtures are never inside a pickupable or behind a door (AI2-THOR lists overlaps too)
                assert not o.hidden, (name, o.id)
        for record in k.placements:
            indices = [r[0] for r in record]
            assert len(set(indices)) == len(indices)
            assert all(k.objects[i].pickupable for i in indices), name


def test_hidden_objects_exist_in_most_kitchens():
    """Actionable targets need objects inside closed receptacles."""
    hidden = {name: sum(o.hidden for o in load_kitchen(name).objects) for name in KITCHEN_NAMES}
    assert 60 <= sum(hidden.values()) <= 120, hidden
    assert sum(n > 0 for n in hidden.values()) >= 25, hidden


def test_summary_counts():
    s = kitchens.kitchen_summary(load_kitchen("FloorPlan1"))
    k = load_kitchen("FloorPlan1")
    assert s == {
        "name": "FloorPlan1",
        "reachable_cells": len(k.reachable),
        "objects": len(k.objects),
        "hidden_objects": sum(o.hidden for o in k.objects),
        "openable_receptacles": sum(o.openable for o in k.objects),
    }
    assert s["reachable_cells"] == 129 and s["hidden_objects"] >= 1
