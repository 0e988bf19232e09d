"""The Allan engine against every Stable32 ADEV/OADEV/MDEV/OHDEV table in ../shared/data/stable32.

Stable32 prints five significant digits, so a correct engine matches to within half a unit
of the last digit (<= 5e-5 relative); 1e-4 is asserted. Confidence bounds are compared at the
noise type printed in the table ("same noise type").
"""

from __future__ import annotations

import gzip
from functools import cache

import numpy as np
import pytest

from imunoise.analysis.allan import allan, identify_noise, phase_from_rate
from imunoise.analysis.edf import LAG1_MIN_POINTS
from tests.shared_paths import SHARED_DATA

DATA = SHARED_DATA / "stable32"

pytestmark = pytest.mark.skipif(
    not DATA.is_dir(), reason="reference data ../shared/data/stable32 not present"
)

# data set -> (file, data type, sampling rate in Hz)
SETS = {
    "phasedat": ("phasedat/PHASE.DAT", "phase", 1.0),
    "ocxo": ("ocxo/ocxo_frequency.txt", "freq", 1.0),
    "pink": ("pink_frequency/pink_frequency.txt", "freq", 1.0 / 42.0),
    "cs5071a": ("Cs5071A/5071A_phase.txt.gz", "phase", 1.0),
    "tic": ("Keysight53230A_ti_noise_floor/tic_phase.txt", "phase", 1.0),
    "gps": ("gps/gps_1pps_phase_data.txt.gz", "phase", 1.0),
}

# (data set, kind, table file)
TABLES = [
    ("phasedat", "adev", "phasedat/phase_dat_adev.txt"),
    ("phasedat", "adev", "phasedat/phase_dat_adev_octave.txt"),
    ("phasedat", "oadev", "phasedat/phase_dat_oadev.txt"),
    ("phasedat", "oadev", "phasedat/phase_dat_oadev_octave.txt"),
    ("phasedat", "mdev", "phasedat/phase_dat_mdev.txt"),
    ("phasedat", "mdev", "phasedat/phase_dat_mdev_octave.txt"),
    ("phasedat", "ohdev", "phasedat/phase_dat_ohdev.txt"),
    ("phasedat", "ohdev", "phasedat/phase_dat_ohdev_octave.txt"),
    ("ocxo", "adev", "ocxo/stable32_adev_alltau.txt"),
    ("ocxo", "oadev", "ocxo/stable32_oadev_alltau.txt"),
    ("ocxo", "mdev", "ocxo/stable32_mdev_alltau.txt"),
    ("ocxo", "ohdev", "ocxo/stable32_ohdev_alltau.txt"),
    ("pink", "adev", "pink_frequency/adev.txt"),
    ("pink", "oadev", "pink_frequency/oadev.txt"),
    ("pink", "oadev", "pink_frequency/s32_oadev_octave.txt"),
    ("pink", "mdev", "pink_frequency/mdev.txt"),
    ("pink", "ohdev", "pink_frequency/ohdev.txt"),
    ("cs5071a", "adev", "Cs5071A/adev_all.txt"),
    ("cs5071a", "adev", "Cs5071A/adev_decade.txt"),
    ("cs5071a", "oadev", "Cs5071A/oadev_all.txt"),
    ("cs5071a", "oadev", "Cs5071A/oadev_decade.txt"),
    ("cs5071a", "mdev", "Cs5071A/mdev_all.txt"),
    ("cs5071a", "mdev", "Cs5071A/mdev_decade.txt"),
    ("cs5071a", "ohdev", "Cs5071A/ohdev_all.txt"),
    ("cs5071a", "ohdev", "Cs5071A/ohdev_decade.txt"),
    ("tic", "adev", "Keysight53230A_ti_noise_floor/tic_adev.txt"),
    ("tic", "oadev", "Keysight53230A_ti_noise_floor/tic_oadev.txt"),
    ("tic", "mdev", "Keysight53230A_ti_noise_floor/tic_mdev.txt"),
    ("tic", "ohdev", "Keysight53230A_ti_noise_floor/tic_ohdev.txt"),
    ("gps", "adev", "gps/stable32_ADEV_decade.txt"),
    ("gps", "oadev", "gps/stable32_OADEV_octave.txt"),
    ("gps", "mdev", "gps/stable32_MDEV_octave.txt"),
    ("gps", "ohdev", "gps/stable32_OHDEV_octave.txt"),
]

# The ocxo octave tables were computed by Stable32 from a different file of the same
# recording ("ocxo_frequency.001", frequency divided by 1e7, so values near 1.0 with the
# fluctuation in the 11th digit); they lost precision there. Their OADEV at m = 1 differs
# from the ADEV at m = 1 of the full-precision tables by 5e-4 although the two estimators are
# identical at m = 1 (checked below). They are compared at 2e-3, the size of that loss.
OCXO_OCTAVE = [
    ("ocxo", "adev", "ocxo/adev_octave.txt"),
    ("ocxo", "oadev", "ocxo/oadev_octave.txt"),
    ("ocxo", "mdev", "ocxo/mdev_octave.txt"),
    ("ocxo", "ohdev", "ocxo/ohdev_octave.txt"),
]
OCXO_OCTAVE_TOL = 2e-3

DEV_TOL = 1e-4
# Stable32 bounds carry 5 digits and use chi-square quantiles of its own; 1e-3 is asserted
# (the requirement is 1e-2).
CI_TOL = 1e-3


@cache
def load_set(name: str) -> np.ndarray:
    path, _, _ = SETS[name]
    p = DATA / path
    opener = gzip.open if p.suffix == ".gz" else open
    with opener(p, "rt") as fh:
        values = [
            float(line.split()[0])
            for line in fh
            if line.strip() and not line.lstrip().startswith(("#", "%"))
        ]
    data = np.array(values)
    if name == "ocxo":
        data = (data - 1e7) / 1e7  # Hz -> fractional frequency
    return data


@cache
def read_table(path: str) -> np.ndarray:
    """Rows of ``AF Tau # Alpha MinSigma Sigma MaxSigma`` (commented-out rows skipped)."""
    rows = []
    for line in (DATA / path).read_text().splitlines():
        parts = line.split()
        if line.startswith("#") or len(parts) != 7:
            continue
        rows.append([float(v) for v in parts])
    return np.array(rows)


@cache
def curve_for(name: str, kind: str, path: str):
    tab = read_table(path)
    _, data_type, fs = SETS[name]
    return allan(
        load_set(name),
        fs,
        kind,
        m=tab[:, 0].astype(np.int64),
        alpha=tab[:, 3].astype(np.int64),
        data_type=data_type,
    )


def _ids(tables):
    return [p.rsplit("/", 1)[-1] for _, _, p in tables]


@pytest.mark.parametrize(("name", "kind", "path"), TABLES, ids=_ids(TABLES))
def test_deviation_and_counts_match_stable32(name, kind, path):
    tab = read_table(path)
    curve = curve_for(name, kind, path)
    np.testing.assert_array_equal(curve.m, tab[:, 0].astype(np.int64))
    np.testing.assert_array_equal(curve.n_terms, tab[:, 2].astype(np.int64))
    # s32_oadev_octave.txt was made with tau0 = 1 s instead of 42 s: compare tau / m
    tau0 = tab[0, 1] / tab[0, 0]
    np.testing.assert_allclose(tab[:, 1], tab[:, 0] * tau0, rtol=1e-4)
    if path != "pink_frequency/s32_oadev_octave.txt":
        np.testing.assert_allclose(curve.tau_s, tab[:, 1], rtol=1e-4)
    np.testing.assert_allclose(curve.dev, tab[:, 5], rtol=DEV_TOL, atol=0)


CI_TABLES = [t for t in TABLES if "octave" in t[2] or "decade" in t[2]]
CI_TABLES += [t for t in TABLES if t[0] == "tic" and t[1] != "adev"]


@pytest.mark.parametrize(("name", "kind", "path"), CI_TABLES, ids=_ids(CI_TABLES))
def test_confidence_bounds_match_stable32(name, kind, path):
    tab = read_table(path)
    assert np.all(tab[:, 4] > 0), "table carries no confidence bounds"
    curve = curve_for(name, kind, path)
    np.testing.assert_allclose(curve.ci_low, tab[:, 4], rtol=CI_TOL, atol=0)
    np.testing.assert_allclose(curve.ci_high, tab[:, 6], rtol=CI_TOL, atol=0)
    assert curve.ci == 0.683


@pytest.mark.parametrize(("name", "kind", "path"), OCXO_OCTAVE, ids=_ids(OCXO_OCTAVE))
def test_ocxo_octave_tables_within_their_precision(name, kind, path):
    tab = read_table(path)
    curve = curve_for(name, kind, path)
    np.testing.assert_array_equal(curve.n_terms, tab[:, 2].astype(np.int64))
    np.testing.assert_allclose(curve.dev, tab[:, 5], rtol=OCXO_OCTAVE_TOL, atol=0)
    np.testing.assert_allclose(curve.ci_low, tab[:, 4], rtol=OCXO_OCTAVE_TOL + CI_TOL)
    np.testing.assert_allclose(curve.ci_high, tab[:, 6], rtol=OCXO_OCTAVE_TOL + CI_TOL)


def test_ocxo_octave_tables_are_inconsistent_with_the_full_precision_ones():
    oadev_1 = read_table("ocxo/oadev_octave.txt")[0, 5]
    adev_1 = read_table("ocxo/stable32_adev_alltau.txt")[0, 5]
    assert read_table("ocxo/oadev_octave.txt")[0, 0] == 1
    assert abs(oadev_1 / adev_1 - 1) > 4e-4


def test_own_noise_identification_agrees_with_stable32():
    """Lag-1 ACF noise ID (no alpha given) against the Alpha column, at taus with at least
    30 averages (Stable32 switches to other methods below that)."""
    agree = total = 0
    for name, kind, path in TABLES + OCXO_OCTAVE:
        tab = read_table(path)
        data = load_set(name)
        _, data_type, fs = SETS[name]
        if data_type == "freq":
            u = phase_from_rate(data)
        else:
            u = (data - data[0]) * fs
        ms = tab[:, 0].astype(np.int64)
        usable = (u.size - 1) // ms >= LAG1_MIN_POINTS
        alpha = identify_noise(u, ms[usable], kind)
        agree += int(np.sum(alpha == tab[usable, 3]))
        total += int(np.sum(usable))
    assert total > 2000
    # measured: 2594 of 2632 (98.6 %); the misses sit where rho is near a rounding edge
    assert agree / total >= 0.98


def test_batch_uses_identified_alpha_when_none_given():
    name, kind, path = "gps", "oadev", "gps/stable32_OADEV_octave.txt"
    tab = read_table(path)
    _, data_type, fs = SETS[name]
    curve = allan(load_set(name), fs, kind, m=tab[:, 0].astype(np.int64), data_type=data_type)
    usable = (load_set(name).size - 1) // curve.m >= LAG1_MIN_POINTS
    assert np.mean(curve.alpha[usable] == tab[usable, 3]) >= 0.8
    # where the identified alpha agrees, so do the bounds
    same = curve.alpha == tab[:, 3]
    np.testing.assert_allclose(curve.ci_low[same], tab[same, 4], rtol=CI_TOL)


# Taus where the identified noise type differs from Stable32's Alpha column, with the reason.
# The OCXO octave tables were computed by Stable32 from a lower-precision copy of the data
# (see OCXO_OCTAVE); the TIC set's last tau has six averages, whose B1 ratio (1.5) is nearest
# white rate noise while Stable32 printed flicker phase noise.
KNOWN_DIFFERENCES = {
    ("ocxo/adev_octave.txt", 2048), ("ocxo/oadev_octave.txt", 4096),
    ("ocxo/mdev_octave.txt", 4096), ("ocxo/ohdev_octave.txt", 4096),
    ("Keysight53230A_ti_noise_floor/tic_oadev.txt", 8192),
    ("Keysight53230A_ti_noise_floor/tic_mdev.txt", 8192),
    ("Keysight53230A_ti_noise_floor/tic_ohdev.txt", 8192),
}


def _rate(name: str) -> tuple[np.ndarray, float]:
    """The set as rate samples (phase data differenced) and its sampling rate."""
    _, data_type, fs = SETS[name]
    data = load_set(name)
    return (data if data_type == "freq" else np.diff(data) * fs), fs


ALL_CI_TABLES = CI_TABLES + OCXO_OCTAVE


@pytest.mark.parametrize(("name", "kind", "path"), ALL_CI_TABLES, ids=_ids(ALL_CI_TABLES))
def test_own_noise_type_and_bounds_match_stable32_at_every_tau(name, kind, path):
    """No alpha given: the engine identifies the noise at every tau (lag-1 ACF with 30 or more
    averages, B1 and R(n) below) and gets Stable32's Alpha column and bounds."""
    tab = read_table(path)
    _, data_type, fs = SETS[name]
    curve = allan(load_set(name), fs, kind, m=tab[:, 0].astype(np.int64), data_type=data_type)
    few = (load_set(name).size - (data_type == "phase")) // curve.m < LAG1_MIN_POINTS
    assert few.any(), "the table has no tau with fewer than 30 averages"
    known = np.array([(path, int(m)) in KNOWN_DIFFERENCES for m in curve.m])
    np.testing.assert_array_equal(curve.alpha[known] != tab[known, 3], True)
    ok = ~known
    np.testing.assert_array_equal(curve.alpha[ok], tab[ok, 3].astype(np.int64))
    tol = CI_TOL + (OCXO_OCTAVE_TOL if name == "ocxo" else 0.0)
    np.testing.assert_allclose(curve.ci_low[ok], tab[ok, 4], rtol=tol, atol=0)
    np.testing.assert_allclose(curve.ci_high[ok], tab[ok, 6], rtol=tol, atol=0)


OADEV_OCTAVE = [t for t in ALL_CI_TABLES if t[1] == "oadev" and "octave" in t[2].lower()]


@pytest.mark.parametrize(("name", "kind", "path"), OADEV_OCTAVE, ids=_ids(OADEV_OCTAVE))
def test_analyze_json_edf_gives_stable32_bounds_at_every_tau(name, kind, path, tmp_path):
    """Through the command line: `imunoise analyze --json` on the set written as a CSV rate
    channel; its edf and alpha rebuild Stable32's 68.3 % bounds at every octave tau."""
    import json
    import subprocess
    import sys

    from scipy import stats

    tab = read_table(path)
    y, fs = _rate(name)
    csv = tmp_path / "set.csv"
    t = np.arange(y.size) / fs
    np.savetxt(csv, np.column_stack([t, y]), delimiter=",", header="t,gyro_x", comments="",
               fmt="%.17g")
    out = subprocess.run([sys.executable, "-m", "imunoise", "analyze", str(csv), "--json"],
                         capture_output=True, text=True, check=True, timeout=600)
    allan_doc = json.loads(out.stdout)["channels"]["gyro_x"]["allan"]
    m = np.rint(np.array(allan_doc["tau_s"]) * fs).astype(np.int64)
    rows = {int(r[0]): r for r in tab}
    common = [j for j, mj in enumerate(m) if mj in rows]
    assert len(common) == len(tab), f"analyze reports m {m.tolist()}, table {list(rows)}"
    dev = np.array(allan_doc["adev"])[common]
    edf = np.array(allan_doc["edf"])[common]
    alpha = np.array(allan_doc["alpha"])[common]
    want = np.array([rows[int(mj)] for mj in m[common]])
    border = np.array([(path, int(mj)) in KNOWN_DIFFERENCES for mj in m[common]])
    np.testing.assert_array_equal(alpha[~border], want[~border, 3].astype(np.int64))
    lo = dev * np.sqrt(edf / stats.chi2.ppf(0.5 + 0.683 / 2, edf))
    hi = dev * np.sqrt(edf / stats.chi2.ppf(0.5 - 0.683 / 2, edf))
    tol = CI_TOL + (OCXO_OCTAVE_TOL if name == "ocxo" else 0.0)
    np.testing.assert_allclose(lo[~border], want[~border, 4], rtol=tol)
    np.testing.assert_allclose(hi[~border], want[~border, 6], rtol=tol)
