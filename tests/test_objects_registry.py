"""Object registry and named object sets (Python API and Hydra configs agree)."""

from pathlib import Path

import numpy as np
import pytest
import yaml

from defgraspnets.objects import (
    CATEGORIES,
    OBJECT_SETS,
    PRIMITIVES,
    REAL_OBJECTS,
    get_object,
    list_objects,
    object_set,
)

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "objects"


def test_lists_and_filters():
    prims = list_objects(source="primitive")
    assert len(prims) == len(PRIMITIVES) >= 60
    assert list_objects(source="real") == list(REAL_OBJECTS)
    assert list_objects() == prims + list(REAL_OBJECTS)
    for c in CATEGORIES:
        names = list_objects(category=c)
        assert names and all(PRIMITIVES[n].category == c for n in names)
    assert set(list_objects(category="fruit")) == {
        n for n, s in REAL_OBJECTS.items() if s.category == "fruit"
    }
    with pytest.raises(ValueError, match="unknown category"):
        list_objects(category="pyramid")
    with pytest.raises(ValueError, match="unknown source"):
        list_objects(source="scan")


def test_object_sets_match_hydra_configs():
    for name in OBJECT_SETS:
        cfg = yaml.safe_load((CONFIGS / f"{name}.yaml").read_text())
        assert cfg["names"] == object_set(name), name
    assert object_set("all") == object_set("primitives") + object_set("real")
    assert len(object_set("ci_small")) == 3 and set(object_set("ci_small")) <= set(PRIMITIVES)
    with pytest.raises(KeyError, match="unknown object set"):
        object_set("everything")


def test_get_object_metadata_and_copy():
    obj = get_object("torus_R30_r10")
    assert obj.category == "torus" and obj.source == "primitive" and "MIT" in obj.license
    assert obj.volume == pytest.approx(2 * np.pi**2 * 0.03 * 0.01**2)
    np.testing.assert_allclose(obj.dims, [0.08, 0.08, 0.02], rtol=1e-3)
    obj.surface.apply_translation([1.0, 0, 0])  # callers may modify their copy ...
    assert np.abs(get_object("torus_R30_r10").surface.center_mass).max() < 1e-9  # ... not the registry's


def test_unknown_object_name():
    with pytest.raises(KeyError, match="unknown object 'torus_huge'.*similar: torus_"):
        get_object("torus_huge")
    # a name that is no string (an unset config value) says so (was "'NoneType' object has no attribute ...")
    with pytest.raises(TypeError, match="object name must be a string .*got None"):
        get_object(None)
