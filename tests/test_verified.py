"""stdr.verified: the one table of where each compiled form is verified, and the rule for CUDA."""
from pathlib import Path

import pytest

from stdr.testing import make_cfg
from stdr.verified import EVIDENCE, VERIFIED, verified_on

ROOT = Path(__file__).resolve().parents[1]


def test_every_entry_is_a_config_key_defaulting_to_null():
    """A listed key is a real `null | true | false` switch: the table steers its null."""
    for key in VERIFIED:
        base = "experiment=embedded_4dgs" if key.startswith("baseline.hexplane") else "experiment=embedded_deform"
        node = make_cfg([base])
        for part in key.split("."):
            node = getattr(node, part)
        assert node is None, key
        assert set(VERIFIED[key]) <= {"cpu", "cuda"} and "cpu" in VERIFIED[key], key


def test_a_cuda_entry_names_its_evidence_and_the_evidence_exists():
    for key, devices in VERIFIED.items():
        if "cuda" in devices:
            assert key in EVIDENCE, f"{key} lists cuda without evidence (docs/install.md: the rule)"
            assert (ROOT / "docs" / "measurements" / EVIDENCE[key] / "README.md").is_file(), EVIDENCE[key]
    assert set(EVIDENCE) <= set(VERIFIED)


def test_the_speed_keys_wait_for_their_full_gpu_runs():
    """The three speed keys crashed a 20k-step GPU run after passing parity (2026-11-27): CUDA
    stays off them until the full-run pair of the rule is recorded."""
    for key in ("optim.fused_loss", "train.guard.compiled", "train.guard.sync_free", "baseline.hexplane.compiled"):
        assert "cuda" not in verified_on(key), key


def test_an_unknown_key_names_the_table():
    with pytest.raises(KeyError, match="stdr.verified.VERIFIED"):
        verified_on("optim.fused_los")
