"""PBARL sections: A, I1, I2 and the torsion constant J as Nastran's beam library defines them.

The second moments are checked against the polygon (shoelace) integrals of
the section outline, the torsion constants against the closed forms they
approximate (Saint-Venant's square, Bredt's thin-walled tube), and the
assembled CBAR against the PBAR of the hand-computed section. pyNastran 1.4
alone gave a BAR no torsion stiffness (J = 0) and a BOX its polar moment.
"""

from __future__ import annotations

import numpy as np
import pytest

from femodel import ModelError, assemble, read_bdf
from femodel._reader_properties import _section, _shear_factor

DECK = """SOL 103
CEND
BEGIN BULK
GRID,1,,0.,0.,0.
GRID,2,,400.,0.,0.
GRID,3,,400.,250.,100.
MAT1,1,210000.,,0.3,7.85-9
{prop}
CBAR,10,7,1,2,0.,0.,1.
CBAR,11,7,2,3,1.,0.,0.
ENDDATA
"""


class _Sec:
    def __init__(self, dim):
        self.dim = dim


def _polygon_moments(pts):
    """Area, centroid (y, z) and centroidal second moments (int y^2 dA, int z^2 dA) of a closed polygon."""
    y, z = np.asarray(pts, float).T
    y1, z1 = np.roll(y, -1), np.roll(z, -1)
    c = y * z1 - y1 * z
    a = c.sum() / 2
    cy, cz = ((y + y1) * c).sum() / (6 * a), ((z + z1) * c).sum() / (6 * a)
    iyy = ((y**2 + y * y1 + y1**2) * c).sum() / 12 - a * cy**2  # int y^2 dA about the centroid
    izz = ((z**2 + z * z1 + z1**2) * c).sum() / 12 - a * cz**2
    return abs(a), (cy, cz), abs(iyy), abs(izz)


def _I_outline(h, b1, b2, tw, t1, t2):
    """I section outline, height along y, web centred on z = 0 (counter-clockwise)."""
    return [(0, -b1 / 2), (0, b1 / 2), (t1, b1 / 2), (t1, tw / 2), (h - t2, tw / 2), (h - t2, b2 / 2),
            (h, b2 / 2), (h, -b2 / 2), (h - t2, -b2 / 2), (h - t2, -tw / 2), (t1, -tw / 2), (t1, -b1 / 2)]


def test_bar_torsion_constant_is_saint_venants():
    # square: J = 0.1406 a^4 (Saint-Venant); thin strip a >> b: J -> a b^3 / 3 (1 - 0.63 b / a)
    A, I1, I2, I12, J = (_section(_Sec([10.0, 10.0]), "BAR", k) for k in range(5))
    assert (A, I1, I2, I12) == pytest.approx((100.0, 1e4 / 12, 1e4 / 12, 0.0))
    assert J == pytest.approx(0.1406 * 1e4, rel=2e-3)
    a, b = 200.0, 4.0
    for dim in ([b, a], [a, b]):  # either side may be the long one
        assert _section(_Sec(dim), "BAR", 4) == pytest.approx(a * b**3 / 3 * (1 - 0.63 * b / a), rel=1e-3)
    # I1 is the moment for bending in plane 1: DIM2 (height) along y, I1 = DIM1 DIM2^3 / 12
    assert _section(_Sec([40.0, 30.0]), "BAR", 1) == pytest.approx(40 * 30**3 / 12)


def test_box_torsion_constant_is_bredts_and_its_moments_the_outline_integrals():
    W, H, t1, t2 = 40.0, 30.0, 2.5, 3.0  # t1 top/bottom walls, t2 side walls
    A, I1, I2, I12, J = (_section(_Sec([W, H, t1, t2]), "BOX", k) for k in range(5))
    # Bredt: J = 4 A_m^2 / oint ds / t over the wall centre line
    Am = (W - t2) * (H - t1)
    assert J == pytest.approx(4 * Am**2 / (2 * (W - t2) / t1 + 2 * (H - t1) / t2), rel=1e-12)
    assert J < I1 + I2  # the polar moment pyNastran returned is too stiff
    outer = _polygon_moments([(-H / 2, -W / 2), (H / 2, -W / 2), (H / 2, W / 2), (-H / 2, W / 2)])
    inner = _polygon_moments([(-H / 2 + t1, -W / 2 + t2), (H / 2 - t1, -W / 2 + t2), (H / 2 - t1, W / 2 - t2),
                              (-H / 2 + t1, W / 2 - t2)])
    assert A == pytest.approx(outer[0] - inner[0])
    assert I1 == pytest.approx(outer[2] - inner[2]) and I2 == pytest.approx(outer[3] - inner[3])
    with pytest.raises(ModelError, match="BOX dimensions"):
        _section(_Sec([W, H, 16.0, t2]), "BOX", 0)


@pytest.mark.parametrize("dim", [[100.0, 60.0, 60.0, 5.0, 8.0, 8.0], [120.0, 80.0, 40.0, 6.0, 10.0, 5.0]],
                         ids=["symmetric", "unequal-flanges"])
def test_i_section_moments_are_the_outline_integrals(dim):
    A, I1, I2, I12, J = (_section(_Sec(dim), "I", k) for k in range(5))
    a, _, iy, iz = _polygon_moments(_I_outline(*dim))
    assert A == pytest.approx(a, rel=1e-12)
    assert I1 == pytest.approx(iy, rel=1e-12)  # about the (shifted) centroid: strong axis
    assert I2 == pytest.approx(iz, rel=1e-12)
    h, b1, b2, tw, t1, t2 = dim
    clear = (b1 * t1**3 + b2 * t2**3 + (h - t1 - t2) * tw**3) / 3  # web between the flanges
    full = (b1 * t1**3 + b2 * t2**3 + h * tw**3) / 3
    assert clear < J < full and I12 == 0.0
    with pytest.raises(ModelError, match="I dimensions"):
        _section(_Sec([10.0, 60.0, 60.0, 5.0, 6.0, 6.0]), "I", 0)


def test_tube2_is_the_tube_of_its_wall():
    tube = [_section(_Sec([10.0, 2.0]), "TUBE2", k) for k in range(5)]
    ro, ri = 10.0, 8.0
    assert tube == pytest.approx([np.pi * (ro**2 - ri**2), np.pi * (ro**4 - ri**4) / 4,
                                  np.pi * (ro**4 - ri**4) / 4, 0.0, np.pi * (ro**4 - ri**4) / 2])


@pytest.mark.parametrize("btype,dim", [("BAR", [40.0, 30.0]), ("BOX", [40.0, 30.0, 2.5, 3.0]),
                                       ("I", [120.0, 80.0, 40.0, 6.0, 10.0, 5.0]), ("TUBE2", [10.0, 2.0])])
def test_pbarl_cbar_assembles_as_the_pbar_of_its_section(tmp_path, btype, dim):
    def mats(prop, name):
        path = tmp_path / name
        path.write_text(DECK.format(prop=prop))
        asm = assemble(read_bdf(path, units="mm-t-s"))
        return asm.stiffness_g().toarray(), asm.mass_g().toarray()

    dims = ",".join(repr(d) for d in dim)
    K1, M1 = mats(f"PBARL,7,1,,{btype}\n,{dims}", "pbarl.bdf")
    A, I1, I2, _, J = (_section(_Sec(dim), btype, k) for k in range(5))
    kf = _shear_factor(btype, dim, A)
    shear = f"\n,,,,,,,,\n,{kf!r},{kf!r}" if np.isfinite(kf) else ""
    K2, M2 = mats(f"PBAR,7,1,{A!r},{I1!r},{I2!r},{J!r}{shear}", "pbar.bdf")
    assert J > 0
    np.testing.assert_allclose(K1, K2, rtol=0, atol=1e-12 * np.abs(K2).max())
    np.testing.assert_allclose(M1, M2, rtol=0, atol=1e-12 * np.abs(M2).max())


def test_a_frame_of_pbarl_bar_posts_has_no_torsion_mechanism(tmp_path):
    """The outside probe's fault: a BAR post twisted freely (J = 0) and the modes failed on negative eigenvalues."""
    path = tmp_path / "posts.bdf"
    path.write_text(DECK.format(prop="PBARL,7,1,,BAR\n,40.,30."))
    asm = assemble(read_bdf(path, units="mm-t-s"))
    K = asm.stiffness_g().toarray()
    # twist of element 10 about its axis (x): rotate grid 2 about x, grid 1 fixed -> a restoring moment
    rx1, rx2 = asm.gset.index(1, 4), asm.gset.index(2, 4)
    assert K[rx2, rx2] > 0 and K[rx1, rx2] < 0
