"""stdr.verified: the one table of where each compiled form is verified, and the rule for CUDA."""
from pathlib import Path

import pytest

from stdr.testing import make_cfg
from stdr.verified import CUDA_RUN_SEEDS, CUDA_RUN_TOLERANCE_DB, EVIDENCE, VERIFIED, cuda_run_verdict, verified_on

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
            assert (ROOT / "research" / "measurements" / EVIDENCE[key] / "README.md").is_file(), EVIDENCE[key]
    assert set(EVIDENCE) <= set(VERIFIED)


def test_the_speed_keys_wait_for_their_full_gpu_runs():
    """The three speed keys crashed a 20k-step GPU run after passing parity (research/notes): CUDA
    stays off them until the full-run pair of the rule is recorded."""
    for key in ("optim.fused_loss", "train.guard.compiled", "train.guard.sync_free", "baseline.hexplane.compiled"):
        assert "cuda" not in verified_on(key), key


def test_an_unknown_key_names_the_table():
    with pytest.raises(KeyError, match="stdr.verified.VERIFIED"):
        verified_on("optim.fused_los")


def test_the_full_run_rule_reads_the_mean_gap_over_every_seed():
    """One pair is not a verdict; the mean over CUDA_RUN_SEEDS is, on either side of the twin."""
    twin = {s: 36.5 + 0.1 * s for s in CUDA_RUN_SEEDS}
    assert len(CUDA_RUN_SEEDS) >= 3 and CUDA_RUN_TOLERANCE_DB == 0.2
    one = cuda_run_verdict({0: twin[0] - 0.05}, twin)
    assert not one["passes"] and one["gap_db"] is None and one["missing"] == list(CUDA_RUN_SEEDS[1:])
    # a seed 0.30 dB low, the others close: the mean decides
    close = {s: twin[s] + d for s, d in zip(CUDA_RUN_SEEDS, (-0.30, 0.05, -0.02))}
    v = cuda_run_verdict(close, twin)
    assert v["passes"] and abs(v["gap_db"] - (-0.27 / 3)) < 1e-9 and abs(v["per_seed"][CUDA_RUN_SEEDS[0]] + 0.30) < 1e-9
    for d in (-0.25, 0.25):  # a systematic gap past the tolerance fails, below or above
        assert not cuda_run_verdict({s: twin[s] + d for s in CUDA_RUN_SEEDS}, twin)["passes"]
