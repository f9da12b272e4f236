"""Snap to plate (core.lips.snap): synthetic images with an edge at a known subpixel position."""

import numpy as np
import pytest
from scipy import ndimage

from facelab_addon.core.lips.snap import snap_lips, snap_stroke, snap_strokes


def area_image(H, W, inside, ss=8, blur=0.7, dark=0.1, light=0.8, noise=0.0, seed=0):
    """(H,W) image of a region drawn with ``ss``x``ss`` supersampling (pixel (i, j) covers [i, i+1] x [j, j+1]),
    ``dark`` where ``inside(x, y)``, blurred by ``blur`` px, plus Gaussian noise."""
    ys, xs = (np.arange(H * ss) + 0.5) / ss, (np.arange(W * ss) + 0.5) / ss
    m = np.broadcast_to(inside(xs[None], ys[:, None]), (H * ss, W * ss))
    img = np.where(m, dark, light).reshape(H, ss, W, ss).mean((1, 3))
    img = ndimage.gaussian_filter(img, blur)
    return img + np.random.default_rng(seed).normal(0.0, noise, img.shape)


@pytest.mark.parametrize("edge_y", [40.0, 40.25, 40.5, 40.8])
def test_straight_edge_found_at_its_subpixel_row(edge_y):
    img = area_image(80, 120, lambda x, y: y > edge_y)
    x = np.linspace(20, 100, 41)
    stroke = np.c_[x, edge_y + 3.0 + 0.5 * np.sin(x / 9)]  # drawn 2.5-3.5 px low
    r = snap_strokes(img, [stroke])[0]
    assert r.n_snapped == len(x) and r.n_left == 0
    np.testing.assert_allclose(r.points[:, 1], edge_y, atol=0.05)
    moved = r.points - stroke
    tangent = np.gradient(stroke, axis=0)
    np.testing.assert_allclose(np.sum(moved * tangent, 1), 0.0, atol=1e-9)  # along the normal only


def test_curved_edge_with_hand_jitter_ends_on_the_line():
    from facelab_addon.testing.route import jitter_stroke

    cx, cy, R = 150.3, 100.7, 60.0
    img = area_image(200, 300, lambda x, y: (x - cx) ** 2 + (y - cy) ** 2 < R * R, noise=0.01)
    a = np.linspace(0.3, 2.8, 80)
    truth = np.c_[cx + R * np.cos(a), cy + R * np.sin(a)]
    for noise, seed in ((2.0, 0), (3.0, 1), (4.0, 2)):
        s = jitter_stroke(truth, noise, np.random.default_rng(seed))
        r = snap_strokes(img, [s])[0]
        before = np.abs(np.hypot(*(s - [cx, cy]).T) - R)
        after = np.abs(np.hypot(*(r.points - [cx, cy]).T) - R)
        assert before.mean() > 0.6
        assert r.n_snapped == len(s)
        assert after.max() < 0.1, (noise, after.max())


def test_no_edge_leaves_points_exactly_and_says_so():
    rng = np.random.default_rng(0)
    noise = rng.normal(0.0, 0.01, (120, 160))
    yy, xx = np.mgrid[:120, :160]
    blurred = 0.5 + 0.1 * np.sin(xx / 25.0) * np.cos(yy / 30.0)  # soft shading, no edge (a defocused region)
    stroke = np.c_[np.linspace(20, 140, 50), 60 + 2 * np.sin(np.linspace(0, 3, 50))]
    for img in (0.5 + noise, blurred + noise, blurred + 0.3 * noise, np.full((120, 160), 0.3),
                np.round(255 * ndimage.gaussian_filter(0.5 + noise, 3.0)) / 255):
        r = snap_strokes(img, [stroke])[0]
        assert r.n_snapped == 0 and r.n_left == 50 and r.polarity == 0
        np.testing.assert_array_equal(r.points, stroke)


def test_edge_on_part_of_the_stroke_only_moves_that_part():
    # the edge (dark below y = 50.4) ends at x = 70; right of it the image is flat
    img = area_image(100, 140, lambda x, y: (y > 50.4) & (x < 70), noise=0.005)
    x = np.linspace(10, 130, 61)
    stroke = np.c_[x, np.full_like(x, 52.5)]
    r = snap_strokes(img, [stroke])[0]
    left, right = x < 60, x > 80
    assert r.snapped[left].all() and not r.snapped[right].any()
    np.testing.assert_allclose(r.points[left, 1], 50.4, atol=0.1)
    np.testing.assert_array_equal(r.points[right], stroke[right])
    assert r.n_left == int((~r.snapped).sum()) >= right.sum()


def test_narrow_mouth_each_stroke_takes_its_own_edge():
    # a dark gap from y = 50.2 to 55.2 between two light lips, both edges within reach of both strokes: the
    # upper stroke (mouth below) takes the top edge, the lower stroke (mouth above) the bottom edge, each drawn
    # 2 px off on the far side
    img = area_image(100, 140, lambda x, y: (y > 50.2) & (y < 55.2), blur=0.5)
    x = np.linspace(20, 120, 41)
    (up,), (lo,) = snap_lips(img, [np.c_[x, np.full_like(x, 48.2)]], [np.c_[x[::-1], np.full_like(x, 57.2)]],
                             lower_corner=0.0)
    np.testing.assert_allclose(up.points[:, 1], 50.2, atol=0.06)
    np.testing.assert_allclose(lo.points[:, 1], 55.2, atol=0.06)
    # told the side, each stroke ignores the other lip's edge even when that one is nearer
    (lo,) = snap_strokes(img, [np.c_[x, np.full_like(x, 51.0)]], mouth_side=(0, -1))
    np.testing.assert_allclose(lo.points[:, 1], 55.2, atol=0.06)
    (up,) = snap_strokes(img, [np.c_[x[::-1], np.full_like(x, 54.5)]], mouth_side=(0, 1))
    np.testing.assert_allclose(up.points[:, 1], 50.2, atol=0.06)


def test_opposite_polarity_is_refused_when_asked():
    img = area_image(80, 120, lambda x, y: y > 40.3)
    stroke = np.c_[np.linspace(20, 100, 30), np.full(30, 42.0)]
    found = snap_stroke(img, stroke)
    assert found.n_snapped == 30
    other = snap_stroke(img, stroke, polarity=-found.polarity)
    assert other.n_snapped == 0
    np.testing.assert_array_equal(other.points, stroke)


def test_search_range_bounds_the_move():
    img = area_image(80, 120, lambda x, y: y > 30.0)
    stroke = np.c_[np.linspace(20, 100, 30), np.full(30, 40.0)]  # 10 px away
    assert snap_strokes(img, [stroke], search_px=6.0)[0].n_snapped == 0
    r = snap_strokes(img, [stroke], search_px=12.0)[0]
    np.testing.assert_allclose(r.points[:, 1], 30.0, atol=0.03)


def test_sealed_lips_are_left_as_drawn():
    # a sealed mouth: the lit upper lip over the shaded lower one, one step edge at y = 50.3 where they meet
    # and no dark interior. The upper stroke finds that edge, but the lower lip's line (drawn at y = 48.5, where
    # its stroke found no edge of its own) is not below it: the lips overlap there, both strokes stay as drawn
    img = area_image(100, 140, lambda x, y: y > 50.3, blur=0.5, light=0.8, dark=0.4, noise=0.003)
    x = np.linspace(20, 120, 41)
    up0, lo0 = np.c_[x, np.full_like(x, 52.5)], np.c_[x[::-1], np.full_like(x, 48.5)]
    assert snap_strokes(img, [up0], mouth_side=(0, 1))[0].n_snapped == 41  # alone, it would move
    (up,), (lo,) = snap_lips(img, [up0], [lo0])
    assert up.n_snapped == lo.n_snapped == 0 and up.polarity == lo.polarity == 0
    np.testing.assert_array_equal(up.points, up0)
    np.testing.assert_array_equal(lo.points, lo0)
    # open by 5 px (a dark interior below the edge down to y = 55.3), the same strokes snap
    img = area_image(100, 140, lambda x, y: (y > 50.3) & (y < 55.3), blur=0.5, noise=0.003)
    (up,), (lo,) = snap_lips(img, [up0], [lo0 + [0, 9.0]], lower_corner=0.0)
    assert up.n_snapped == lo.n_snapped == 41
    np.testing.assert_allclose(up.points[:, 1], 50.3, atol=0.1)
    np.testing.assert_allclose(lo.points[:, 1], 55.3, atol=0.1)


def test_lip_edge_in_colour_only_is_found_where_grey_barely_changes():
    # a red lip (above y = 40.4) over a dark-green mouth of nearly the same luminance: the grey edge is weak,
    # the lip-to-mouth colour contrast is strong
    H, W = 80, 120
    m = area_image(H, W, lambda x, y: y > 40.4, dark=0.0, light=1.0, blur=0.6)
    lip, mouth = np.array([0.55, 0.12, 0.10]), np.array([0.05, 0.26, 0.12])
    img = m[..., None] * lip + (1 - m[..., None]) * mouth
    img = img + np.random.default_rng(1).normal(0, 0.01, img.shape)
    assert abs((lip - mouth) @ [0.2126, 0.7152, 0.0722]) < 0.01
    grey = img @ [0.2126, 0.7152, 0.0722]
    assert snap_strokes(grey, [np.c_[np.linspace(20, 100, 41), np.full(41, 43.0)]], mouth_side=(0, 1))[0].n_snapped == 0
    stroke = np.c_[np.linspace(20, 100, 41), 43.0 + np.sin(np.linspace(0, 3, 41))]
    (r,) = snap_strokes(img, [stroke], mouth_side=(0, 1))
    assert r.n_snapped == len(stroke)
    np.testing.assert_allclose(r.points[:, 1], 40.4, atol=0.1)


def test_defocused_edge_is_no_edge():
    # a strong lip edge blurred by 6 px (a defocused plate): no sharp edge, the stroke is left as drawn
    img = area_image(100, 140, lambda x, y: y > 50.0, blur=6.0, noise=0.003)
    stroke = np.c_[np.linspace(20, 120, 41), np.full(41, 52.0)]
    (r,) = snap_strokes(img, [stroke], mouth_side=(0, 1))
    assert r.n_snapped == 0
    np.testing.assert_array_equal(r.points, stroke)
    sharp = area_image(100, 140, lambda x, y: y > 50.0, blur=0.7, noise=0.003)
    assert snap_strokes(sharp, [stroke], mouth_side=(0, 1))[0].n_snapped == 41


def test_a_short_faint_stretch_moves_with_the_edge_a_long_one_stays():
    # the lip edge at y = 40.3 is flat grey for 7 px around x = 50 (a faint stretch) and gone from x = 80 on
    img = area_image(80, 140, lambda x, y: (y > 40.3) & (x < 80), noise=0.003)
    img[:, 47:54] = 0.45
    x = np.linspace(10, 130, 121)  # 1 px apart
    stroke = np.c_[x, np.full_like(x, 42.5)]
    (r,) = snap_strokes(img, [stroke], mouth_side=(0, 1))
    short = np.abs(x - 50.5) <= 1.0
    on = (x < 75) & ~(np.abs(x - 50.5) < 6)
    assert r.snapped[short].all() and r.snapped[on].all()
    np.testing.assert_allclose(r.points[on, 1], 40.3, atol=0.1)
    np.testing.assert_allclose(r.points[short, 1], 40.3, atol=0.3)  # set by its neighbours on the edge
    far = x > 95
    assert not r.snapped[far].any()
    np.testing.assert_array_equal(r.points[far], stroke[far])
    # without bridging, the faint stretch stays where it was drawn
    (r0,) = snap_strokes(img, [stroke], mouth_side=(0, 1), bridge_px=0)
    assert not r0.snapped[short].any()
    np.testing.assert_array_equal(r0.points[short], stroke[short])


def test_crease_between_touching_lips_is_left_as_drawn():
    # the lips touch along a dark crease 2 px wide: its two sides are no inner-lip lines, both strokes stay as
    # drawn (and say so); the same strokes over a 6 px open mouth snap onto its edges
    x = np.linspace(20, 120, 41)
    up0, lo0 = np.c_[x, np.full_like(x, 48.7)], np.c_[x[::-1], np.full_like(x, 53.7)]
    crease = area_image(100, 140, lambda x, y: (y > 50.2) & (y < 52.2), blur=0.5)
    (up,), (lo,) = snap_lips(crease, [up0], [lo0])
    np.testing.assert_array_equal(up.points, up0)
    np.testing.assert_array_equal(lo.points, lo0)
    assert up.n_snapped == lo.n_snapped == 0 and up.n_sealed == 41 and lo.n_sealed == 41
    mouth = area_image(100, 140, lambda x, y: (y > 50.2) & (y < 56.2), blur=0.5)
    (up,), (lo,) = snap_lips(mouth, [up0], [lo0 + [0.0, 2.0]], lower_corner=0.0)
    np.testing.assert_allclose(up.points[:, 1], 50.2, atol=0.06)
    np.testing.assert_allclose(lo.points[:, 1], 56.2, atol=0.06)


def test_lower_lip_snaps_only_part_way_near_the_mouth_corners():
    # the mouth spans x = 20..120 (both strokes); the lower lip's move ramps from nothing at each corner to all
    # of it `lower_corner` of the width in; the upper lip moves all the way everywhere
    img = area_image(100, 140, lambda x, y: (y > 50.2) & (y < 58.2), blur=0.5)
    x = np.linspace(20, 120, 51)
    up0, lo0 = np.c_[x, np.full_like(x, 48.2)], np.c_[x[::-1], np.full_like(x, 60.2)]
    (up,), (lo,) = snap_lips(img, [up0], [lo0], lower_corner=0.2)
    np.testing.assert_allclose(up.points[:, 1], 50.2, atol=0.06)
    share = np.clip(np.minimum(lo0[:, 0] - 20, 120 - lo0[:, 0]) / 20.0, 0, 1)
    np.testing.assert_allclose(lo.points[:, 1], 60.2 - 2.0 * share, atol=0.06)
    np.testing.assert_array_equal(lo.points[[0, -1]], lo0[[0, -1]])
    np.testing.assert_allclose(lo.points[:, 0], lo0[:, 0], atol=1e-9)
    (lo_full,) = snap_lips(img, [up0], [lo0], lower_corner=0.0)[1]
    np.testing.assert_allclose(lo_full.points[:, 1], 58.2, atol=0.06)
