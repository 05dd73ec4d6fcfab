"""Every kind of product flightsim writes, pinned on the CPU before the refactor of the config format.

Each case of ``pin_products.CASES`` (a small run of a product-writing command) runs on the CPU and its
products' digests must equal ``data/product_pins_cpu.json`` exactly: LAS/LAZ/COPC bytes, every HDF5
dataset and attribute, GeoTIFF bytes and bands, the range PNG's pixels, the JSON summaries and CSV tables
less their run times. After the refactor only the command lines and config keys in ``CASES`` may change.
Regenerate the pins (only for an intended change of the products) with
``python3 tests/pin_products.py --device cpu --out tests/data/product_pins_cpu.json``.
"""
import json

import pytest

import pin_products

PINS = json.loads(pin_products.pin_path("cpu").read_text())


def test_every_case_is_pinned():
    assert sorted(pin_products.CASES) == sorted(k for k in PINS if not k.startswith("_"))


@pytest.mark.parametrize("case", list(pin_products.CASES))
def test_products_equal_their_pins(tmp_path, case):
    got = pin_products.run_case(case, "cpu", tmp_path)
    differences = pin_products.compare_case(case, PINS[case], got, "cpu")
    if differences:
        pytest.fail(f"{len(differences)} difference(s) from the pins:\n" + "\n".join(differences[:40]), pytrace=False)
