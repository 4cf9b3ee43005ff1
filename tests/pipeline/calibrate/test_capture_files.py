"""Which files make a Gray-code capture: frames named by the camera, image lists (pipeline/calibrate/capture_files)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ringscan.pipeline.calibrate.capture_files import list_capture, natural_key
from ringscan.pipeline.calibrate.capture_reader import read_capture_files
from ringscan.pipeline.calibrate.errors import CalibrationError
from ringscan.pipeline.calibrate.graycode import decode_graycode, subpixel_map
from tests.support.synthetic_captures import SMALL_PROJECTOR

PROJ = SMALL_PROJECTOR  # the capture fixture's projector (tests/pipeline/calibrate/conftest.py)


def _renamed(src, dst, names):
    """The capture's graycode_NN frames copied to ``names`` (in capture order)."""
    import shutil

    dst.mkdir()
    frames = sorted(src.glob("graycode_*.png"))
    for p, n in zip(frames, names):
        shutil.copy(p, dst / n)
    return frames


def test_frames_named_by_the_camera_are_taken_in_natural_name_order(capture, tmp_path):
    # DSC8 .. DSC37: in plain string order DSC10 .. DSC19 would come before DSC8 and the capture be garbled
    folder, u, v = capture
    names = [f"DSC{k}.PNG" for k in range(8, 38)]
    frames = _renamed(folder, tmp_path / "cap", names)
    files = list_capture(tmp_path / "cap", projector=PROJ)
    assert files.kind == "named" and [p.name for p in files.cameras[0]] == names
    assert sorted(names) != names  # (the plain sort would not do)
    a = read_capture_files(files.cameras[0], projector=PROJ)
    b = read_capture_files(frames, projector=PROJ)
    assert np.array_equal(a.col_pairs, b.col_pairs) and np.array_equal(a.white, b.white)
    dec = subpixel_map(a, decode_graycode(a))
    assert np.sqrt(np.mean((dec.u[dec.subpixel] - u[dec.subpixel]) ** 2)) < 0.08  # as the graycode_NN import


def test_natural_order_compares_numbers_as_numbers():
    names = ["DSC10.JPG", "dsc2.jpg", "DSC1.JPG", "img_2_b.png", "img_10_a.png", "img_2_a.png"]
    assert sorted(names, key=natural_key) == ["DSC1.JPG", "dsc2.jpg", "DSC10.JPG", "img_2_a.png", "img_2_b.png",
                                              "img_10_a.png"]


def test_frames_of_other_names_that_do_not_fit_say_what_the_layout_expects(capture, tmp_path):
    folder, _, _ = capture
    names = [f"DSC{k:05d}.png" for k in range(4052, 4052 + 29)]  # one frame short of 30
    _renamed(folder, tmp_path / "cap", names)
    with pytest.raises(CalibrationError) as e:
        list_capture(tmp_path / "cap", projector=PROJ)
    msg = str(e.value)
    assert msg.startswith(f"{tmp_path / 'cap'}: no frames named graycode_NN")
    assert ("found 29 image(s) of other names (DSC04052.png .. DSC04080.png), but a 128x96 projector in layout "
            "opencv-graycode has 30 (7 column and 7 row bits") in msg, msg


def test_a_plain_text_list_reads_as_a_filestorage_list(capture, tmp_path, monkeypatch):
    folder, _, _ = capture
    frames = sorted(folder.glob("graycode_*.png"))
    sub = tmp_path / "lists"
    sub.mkdir()
    # relative paths beside the list, one absolute, blank lines and comments; CRLF line ends
    lines = ["# capture of the target, camera 1", ""]
    for k, p in enumerate(frames):
        lines.append(str(p) if k == 0 else f"../frames/{p.name}" + ("  # white" if k == len(frames) - 2 else ""))
    (tmp_path / "frames").mkdir()
    for p in frames[1:]:
        (tmp_path / "frames" / p.name).write_bytes(p.read_bytes())
    lst = sub / "capture.txt"
    lst.write_text("\r\n".join(lines) + "\r\n")
    with pytest.raises(CalibrationError, match=r"line 31: \.\./frames/graycode_28\.png  # white not found"):
        list_capture(lst, projector=PROJ)  # a comment after a path is part of the path: only whole lines are
    lines[-2] = lines[-2].split("  #")[0]
    lst.write_text("\r\n".join(lines) + "\r\n")
    files = list_capture(lst, projector=PROJ)
    assert files.kind == "text" and [p.name for p in files.cameras[0]] == [p.name for p in frames]
    assert files.cameras[0][0] == frames[0] and files.cameras[0][1] == sub / "../frames" / frames[1].name
    # not beside the list: the current folder
    monkeypatch.chdir(tmp_path)
    lst2 = tmp_path / "elsewhere" / "c.lst"
    lst2.parent.mkdir()
    lst2.write_text("\n".join(str(Path("frames") / p.name) if k else str(p) for k, p in enumerate(frames)))
    assert list_capture(lst2, projector=PROJ).cameras[0][1] == (tmp_path / "frames" / frames[1].name)
    # a count that does not fit, a missing file, a line that is no image: one line each, naming the list
    lst.write_text("\n".join(str(p) for p in frames[:-1]))
    with pytest.raises(CalibrationError, match=r"capture\.txt: lists 29 frames, but a 128x96 projector .* has 30"):
        list_capture(lst, projector=PROJ)
    lst.write_text("\n".join(["nothere.png"] + [str(p) for p in frames[1:]]))
    with pytest.raises(CalibrationError, match=r"capture\.txt: line 1: nothere\.png not found"):
        list_capture(lst, projector=PROJ)
    lst.write_text("\n".join([str(lst)] + [str(p) for p in frames[1:]]))
    with pytest.raises(CalibrationError, match=r"line 1: .*capture\.txt is not a PNG, TIFF, JPEG or BMP file name"):
        list_capture(lst, projector=PROJ)
    lst.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(CalibrationError, match="not a text image list"):
        list_capture(lst, projector=PROJ)
