"""The virtual rig computes the projector's light over the window of its image that the camera sees
(VirtualRig.emit_window): the same bytes as over the whole image, the same camera frames."""

import dataclasses

import numpy as np
import pytest

from ringscan.pipeline.codecs.render import render_frames
from ringscan.pipeline.formats.patterns import parse_patterns
from ringscan.pipeline.formats.rig import default_rig
from ringscan.pipeline.simulate.virtual_rig import RenderSettings, VirtualRig
from tests.support.tiny_scan import TINY_PATTERNS, tiny_rig


def _emitted_whole(vr, f):
    """The emitted light as the virtual rig computed it before the window (commit 0462968): the whole frame
    through the response, blurred by OpenCV in rows then columns, each fine sample's filter interleaved."""
    import cv2

    from ringscan.pipeline.simulate.virtual_rig import _pixel_gauss_weights

    e = ((np.arange(256) / 255.0) ** float(vr.rig.light.gamma)).astype(np.float32)[f]
    if vr.settings.defocus_px <= 0:
        return e
    k, (ph, pw) = 4, f.shape
    w = _pixel_gauss_weights(vr.settings.defocus_px, k)
    tmp = np.empty((ph, pw * k), np.float32)
    for m in range(k):
        tmp[:, m::k] = cv2.filter2D(e, cv2.CV_32F, w[m][None, :], borderType=cv2.BORDER_CONSTANT)
    out = np.empty((ph * k, pw * k), np.float32)
    for m in range(k):
        out[m::k, :] = cv2.filter2D(tmp, cv2.CV_32F, w[m][:, None], borderType=cv2.BORDER_CONSTANT)
    return out


def _with_projector(rig, width, height):
    return dataclasses.replace(rig, light=dataclasses.replace(rig.light, width=width, height=height))


@pytest.mark.parametrize("size", [(1024, 768), (250, 190)], ids=["default", "odd-width"])
@pytest.mark.parametrize("defocus", [0.7, 2.5, 0.0])
def test_a_windows_emitted_light_is_the_whole_images_bytes(size, defocus):
    """The whole image's light is what the rig computed before it computed windows; any window, at the image's
    edges or inside it, of a projector whose width is a multiple of OpenCV's vector blocks or not: the blurred
    light there is the whole image's, bit for bit (the blur reads the same pixels beyond the window, through
    the same code path; without defocus it is a lookup)."""
    vr = VirtualRig(_with_projector(default_rig(), *size), "plane", settings=RenderSettings(defocus_px=defocus),
                    device="cpu")
    pw, ph = size
    rng = np.random.default_rng(31)
    f = rng.integers(0, 256, (ph, pw), dtype=np.uint8)
    whole = vr.emitted(f)
    assert np.array_equal(whole, _emitted_whole(vr, f))  # the whole image: as before
    k = vr.emitted_upsample
    windows = [(0, 0, pw, ph), (0, 0, 1, 1), (pw - 1, ph - 1, pw, ph), (3, 5, pw, 9), (0, ph // 2, 17, ph)]
    for _ in range(20):
        (x0, x1), (y0, y1) = np.sort(rng.choice(pw + 1, 2, replace=False)), np.sort(rng.choice(ph + 1, 2, replace=False))
        windows.append((int(x0), int(y0), int(x1), int(y1)))
    for x0, y0, x1, y1 in windows:
        part = vr._emitted_window(f, (x0, y0, x1, y1))
        assert part.shape == ((y1 - y0) * k, (x1 - x0) * k)
        assert np.array_equal(part, whole[y0 * k:y1 * k, x0 * k:x1 * k]), (x0, y0, x1, y1)


def _cut_camera(rig, x0, y0, width, height):
    """The rig's camera cut to ``width`` x ``height`` of its pixels from (x0, y0)."""
    K = rig.camera.K.copy()
    K[:2, 2] -= [x0, y0]
    return dataclasses.replace(rig, camera=dataclasses.replace(rig.camera, width=width, height=height, K=K))


@pytest.mark.parametrize("bit_depth", [8, 16])
def test_frames_rendered_through_the_window_are_the_whole_projectors(bit_depth, device):
    """The tiny rig's camera cut to its middle 32x24 pixels sees a small part of the projector: the render
    computes the light there alone, and every frame of a pattern set (rings and sectors, their edges
    blurred) is byte for byte the render through the whole projector's light, at two turntable angles
    (the window follows the view); on the CPU, where the kernel reads the light in place, and on a GPU."""
    rig = _cut_camera(tiny_rig(), 64, 52, 32, 24)
    frames = list(render_frames(parse_patterns({**TINY_PATTERNS, "bits": 2, "sector_bits": 3})).values())
    settings = RenderSettings(bit_depth=bit_depth)
    cut = VirtualRig(rig, "cube", settings=settings, device=device)
    whole = VirtualRig(rig, "cube", settings=settings, device=device)
    pw, ph = whole.projector_size
    whole.emit_window = lambda: (0, 0, pw, ph)  # the light of the whole image, as before the window
    windows = []
    for deg in (0.0, 45.0):
        cut.set_turntable(deg)
        whole.set_turntable(deg)
        for i, f in enumerate(frames):
            a, b = cut.render(f, seed=i), whole.render(f, seed=i)
            assert a.dtype == b.dtype == (np.uint8 if bit_depth == 8 else np.uint16)
            assert np.array_equal(a, b), (deg, i, np.count_nonzero(a != b))
            assert a.std() > 0  # the frames show the patterns: light the window must hold
        x0, y0, x1, y1 = cut.emit_window()
        windows.append((x0, y0, x1, y1))
        assert 0 < x0 < x1 < pw and 0 < y0 < y1 < ph and (x1 - x0) * (y1 - y0) < 0.1 * pw * ph, (x0, y0, x1, y1)
    assert windows[0] != windows[1]


def test_the_window_holds_every_sub_sample_the_projector_lights():
    """Every sub-sample of a camera pixel that the light may reach (a direct weight, a position on the
    projector's image) lies in the window, at least one projector pixel inside it where the window is
    not at the image's edge (the bilinear reads between the fine samples)."""
    vr = VirtualRig(_cut_camera(default_rig(), 480, 384, 320, 256), "sphere", device="cpu")
    s = vr.geometry().samples.numpy()
    pw, ph = vr.projector_size
    on = (s[:, 2] > 0) & (s[:, 0] >= -0.5) & (s[:, 0] <= pw - 0.5) & (s[:, 1] >= -0.5) & (s[:, 1] <= ph - 0.5)
    x0, y0, x1, y1 = vr.emit_window()
    u, v = s[on, 0], s[on, 1]
    assert on.sum() > 0.9 * 320 * 256 * 4
    assert u.min() >= x0 + 1 and u.max() <= x1 - 2 and v.min() >= y0 + 1 and v.max() <= y1 - 2
    assert (x1 - x0) * (y1 - y0) < 0.15 * pw * ph  # the default rig's middle 320x256: a small part of the image


def test_a_camera_that_sees_no_projector_light_renders_the_ambient_light():
    """A projector image that lights nothing the camera sees (moved far off to the side): an empty window,
    and the frames are the whole projector's (ambient light alone)."""
    rig = default_rig()
    rig = dataclasses.replace(rig, light=dataclasses.replace(rig.light, axis_px=rig.light.axis_px + [5000.0, 0.0]))
    rig = _cut_camera(rig, 480, 384, 64, 48)
    vr = VirtualRig(rig, "sphere", device="cpu")
    assert vr.emit_window() == (0, 0, 0, 0)
    white = np.full(vr.projector_size[::-1], 255, np.uint8)
    whole = VirtualRig(rig, "sphere", device="cpu")
    whole.emit_window = lambda: (0, 0, *vr.projector_size)
    assert np.array_equal(vr.render(white, seed=1), whole.render(white, seed=1))
    assert np.array_equal(vr.render(white, seed=2), vr.render(np.zeros_like(white), seed=2))


def test_rigs_of_one_scene_share_its_corner_normals():
    """The shading normals of a mesh are computed once for the rigs that render it (two cameras, scan after
    scan): the same values as computing them afresh, one read-only array; another mesh gets its own."""
    from ringscan.pipeline.simulate.scenes import corner_normals, make_scene

    sphere = make_scene("sphere")
    a = VirtualRig(tiny_rig(), sphere, device="cpu")
    b = VirtualRig(tiny_rig(), make_scene("sphere"), device="cpu")
    assert a._corner is b._corner and not a._corner.flags.writeable
    assert np.array_equal(a._corner, corner_normals(sphere.vertices, sphere.faces))
    cube = VirtualRig(tiny_rig(), "cube", device="cpu")
    assert cube._corner.shape == (12, 3, 3)
    assert np.array_equal(cube._corner, corner_normals(cube.scene.vertices, cube.scene.faces))


def test_a_perspective_projectors_window_gives_its_whole_frames():
    """The default rig's perspective projector (its lens distortion included), seen by the middle 64x48 pixels
    of its camera: a window of its image, and the frames of the whole image byte for byte."""
    rig = _cut_camera(default_rig(light_model="perspective"), 608, 488, 64, 48)
    spec = parse_patterns({"codec": "gray-rings", "width": 1024, "height": 768, "center": [511.5, 383.5],
                           "rho0": 8.0, "pitch": 4.0, "bits": 2, "sector_bits": 2})
    cut = VirtualRig(rig, "sphere", device="cpu")
    whole = VirtualRig(rig, "sphere", device="cpu")
    whole.emit_window = lambda: (0, 0, 1024, 768)
    x0, y0, x1, y1 = cut.emit_window()
    assert (x1 - x0) * (y1 - y0) < 0.05 * 1024 * 768, (x0, y0, x1, y1)
    for i, f in enumerate(render_frames(spec).values()):
        a = cut.render(f, seed=i)
        assert np.array_equal(a, whole.render(f, seed=i)), i
    assert a.std() > 0
