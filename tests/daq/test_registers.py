"""The register field descriptor shared by drivers and simulators."""

from __future__ import annotations

import numpy as np
import pytest

from imunoise.daq.drivers import adis16350 as adis
from imunoise.daq.drivers import adxl345 as ax
from imunoise.daq.drivers import itg3200 as itg
from imunoise.daq.registers import Field, RegisterMap


def test_signed_field_with_flags_above_it() -> None:
    f = Field("X", 0x04, bits=14, signed=True, scale=0.5, unit="u")
    assert f.count_range == (-8192, 8191)
    assert f.counts(np.array([0x3FFF, 0xC001, 0x2000])).tolist() == [-1, 1, -8192]
    assert f.decode(0x8002) == pytest.approx(1.0)  # flag bits 15, 14 ignored
    assert f.from_si(np.array([-1e9, 0.24, 0.26, 1e9])).tolist() == [-8192, 0, 1, 8191]
    assert f.encode(-1, word=0xC000) == 0xFFFF  # flags kept, data two's complement


def test_sub_register_fields_share_an_address() -> None:
    fs_sel = itg.REGISTERS["FS_SEL"]
    dlpf = itg.REGISTERS["DLPF_CFG"]
    word = int(fs_sel.encode(3, dlpf.encode(5)))
    assert word == 0x1D and itg.dlpf_fs_value(5) == word
    assert fs_sel.counts(word) == 3 and dlpf.counts(word) == 5
    assert itg.is_itg3200_id(0x69) and not itg.is_itg3200_id(0xE5)


@pytest.mark.parametrize(("regs", "names"), [(itg.REGISTERS, itg.DATA_FIELDS),
                                             (ax.REGISTERS, ax.DATA_FIELDS)])
def test_bursts_round_trip_in_bus_byte_order(regs: RegisterMap, names: tuple) -> None:
    counts = [-32768, -1, 0, 32767][:len(names)]
    data = regs.block_bytes(names, counts)
    assert regs.block_counts(names, np.array(data)).tolist() == [counts]
    first = regs[names[0]]
    low_first = data[0] == (counts[0] & 0xFF)
    assert low_first == (not first.big_endian)


def test_scales_are_the_datasheets() -> None:
    deg, g0 = np.pi / 180.0, 9.80665
    assert itg.REGISTERS["GYRO_XOUT"].scale == pytest.approx(deg / 14.375)
    assert itg.REGISTERS["TEMP_OUT"].decode(0xCC70) == pytest.approx(35.0)  # -13200 LSB
    assert ax.REGISTERS["DATAY"].scale == pytest.approx(g0 / 256.0)
    assert ax.data_field("DATAX", ax.data_format(2)).count_range == (-512, 511)
    assert ax.data_field("DATAX", 0x00).scale == pytest.approx(g0 / 256.0)
    assert ax.data_field("DATAX", 0x03).scale == pytest.approx(8 * g0 / 256.0)  # 10-bit, 16 g
    assert adis.REGISTERS["XACCL_OUT"].scale == pytest.approx(2.522e-3 * g0)
    assert adis.gyro_field("XGYRO_OUT", 75).scale == pytest.approx(0.018315 * deg)
    assert adis.ADDR["COMMAND"] == 0x3E and len(adis.REGISTERS) == 31


def _field_by_field(regs: RegisterMap, names: tuple, data: np.ndarray) -> np.ndarray:
    """A burst decoded one field at a time, the definition the fast decoder must match."""
    b = np.asarray(data, dtype=np.int64).reshape(-1, sum(regs[n].nbytes for n in names))
    cols, at = [], 0
    for n in names:
        f = regs[n]
        cols.append(f.counts(f.words_from_bytes(b[:, at:at + f.nbytes])))
        at += f.nbytes
    return np.stack(cols, axis=1)


@pytest.mark.parametrize(("regs", "names"), [
    (itg.REGISTERS, itg.DATA_FIELDS), (ax.REGISTERS, ax.DATA_FIELDS),
    (RegisterMap([Field("A", 0, bits=10, shift=3, signed=True, big_endian=False),
                  Field("B", 2, bits=12, signed=False, big_endian=False)]), ("A", "B")),
    (RegisterMap([Field("A", 0, bits=12, signed=True), Field("C", 2, bits=6, signed=True,
                                                               nbytes=1)]), ("A", "C"))])
def test_a_burst_decodes_as_its_fields_do_one_by_one(regs: RegisterMap, names: tuple) -> None:
    rng = np.random.default_rng(5)
    width = sum(regs[n].nbytes for n in names)
    data = rng.integers(0, 256, size=(200, width))
    expected = _field_by_field(regs, names, data)
    assert np.array_equal(regs.block_counts(names, data), expected)
    assert regs.block_counts(names, data[7].tolist()).tolist() == [expected[7].tolist()]


@pytest.mark.parametrize("field", [Field("S", 0, bits=14, signed=True, scale=0.5),
                                   Field("U", 0, bits=12, shift=2, scale=0.25, offset=-3.0),
                                   itg.REGISTERS["TEMP_OUT"], itg.REGISTERS["DLPF_CFG"]])
def test_one_word_gives_what_an_array_of_words_gives(field: Field) -> None:
    rng = np.random.default_rng(6)
    words = rng.integers(0, 1 << 16, size=300)
    assert [int(field.counts(int(w))) for w in words] == field.counts(words).tolist()
    assert [int(field.counts(w)) for w in words] == field.counts(words).tolist()
    lo, hi = field.count_range
    values = field.offset + field.scale * np.concatenate([
        rng.uniform(lo - 50, hi + 50, 300), np.arange(lo, hi, 7) + 0.5])  # halves included
    assert [int(field.from_si(float(v))) for v in values] == field.from_si(values).tolist()
    counts = rng.integers(lo, hi + 1, size=300)
    assert [int(field.encode(int(c), int(w))) for c, w in zip(counts, words, strict=True)] \
        == field.encode(counts, words).tolist()
