"""io/video.py: probing, sharp-frame selection and extraction on a tiny lossless H.264 video."""
import cv2
import numpy as np
import pytest

from ibr_pipeline.errors import InputError
from ibr_pipeline.io import video
from ibr_pipeline.io.images import read_image

W, H, N, FPS = 64, 48, 24, 10
TARGET = 6                   # windows of 4 frames: [0, 4), [4, 8), ...
SHARP = [1, 6, 8, 15, 17, 22]  # one unblurred frame per window


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """(path, frames): every frame blurred except those in SHARP."""
    import imageio_ffmpeg

    rng = np.random.default_rng(7)
    frames = []
    for i in range(N):
        blocks = (rng.random((H // 4, W // 4, 3)) * 255).astype(np.uint8)
        f = cv2.resize(blocks, (W, H), interpolation=cv2.INTER_NEAREST)  # hard edges: sharp
        if i not in SHARP:
            f = cv2.GaussianBlur(f, (0, 0), 2.0)
        frames.append(np.ascontiguousarray(f))
    path = tmp_path_factory.mktemp("video") / "clip.mp4"
    # lossless H.264 (-qp 0) in 4:4:4, so decoded frames differ from these only by YUV rounding
    w = imageio_ffmpeg.write_frames(str(path), (W, H), fps=FPS, codec="libx264", quality=None,
                                    pix_fmt_out="yuv444p", output_params=["-qp", "0"],
                                    macro_block_size=1)
    w.send(None)
    for f in frames:
        w.send(f)
    w.close()
    return path, frames


@pytest.fixture
def truncated(clip, tmp_path):
    data = clip[0].read_bytes()
    path = tmp_path / "cut.mp4"
    path.write_bytes(data[: len(data) // 2])
    return path


def test_probe(clip):
    assert video.probe(clip[0]) == (N, float(FPS), W, H)


def test_sharp_frames_pick_the_unblurred_frame_of_each_window(clip):
    assert video.sharp_frames(clip[0], TARGET) == SHARP
    assert video.sharp_frames(clip[0], TARGET) == SHARP  # deterministic
    assert video.sharp_frames(clip[0], N + 5) == list(range(N))
    one = video.sharp_frames(clip[0], 1)  # one window: the whole video
    assert len(one) == 1 and one[0] in SHARP
    with pytest.raises(InputError, match=">= 1"):
        video.sharp_frames(clip[0], 0)


def test_extract_frames_match_the_source(clip, tmp_path):
    path, frames = clip
    idx = [SHARP[1], 0, N - 1]
    names = ["a.png", "sub/b.png", "c.png"]
    video.extract_frames(path, idx, tmp_path, names)
    for i, nm in zip(idx, names):
        got = read_image(tmp_path / nm)
        assert got.shape == (H, W, 3)
        assert np.abs(got - frames[i] / 255.0).mean() < 3 / 255
    assert not list(tmp_path.rglob(".*"))  # atomic writes leave no temporary files
    with pytest.raises(InputError, match=rf"clip\.mp4: the video ended after {N} frames"):
        video.extract_frames(path, [N + 3], tmp_path, ["d.png"])


def test_read_video_capture(clip):
    cap = video.read_video(clip[0], TARGET)
    assert cap.format == "video" and cap.files == (clip[0],)
    assert [f.name for f in cap.frames] == [f"frame_{i:05d}.png" for i in SHARP]
    assert cap.frames[0].name == "frame_00001.png"
    assert all(f.image == clip[0] and f.cam_from_world is None and f.lens is None for f in cap.frames)
    assert [f.video_frame for f in cap.frames] == SHARP
    assert f"{TARGET} of {N} frames chosen (sharpest in each window)" in cap.notes


def test_truncated_or_missing_video_is_an_input_error(truncated, tmp_path):
    for call in (video.probe, lambda p: video.sharp_frames(p, 3), lambda p: video.read_video(p, 3),
                 lambda p: video.extract_frames(p, [0], tmp_path, ["x.png"])):
        with pytest.raises(InputError, match=r"cut\.mp4: cannot decode video \(.+\)"):
            call(truncated)
    with pytest.raises(InputError, match=r"gone\.mp4: video file not found"):
        video.probe(tmp_path / "gone.mp4")
    (tmp_path / "text.mov").write_text("not a video\n" * 20)
    with pytest.raises(InputError, match=r"text\.mov: cannot decode video"):
        video.read_video(tmp_path / "text.mov", 3)


def test_extensions():
    assert video.VIDEO_EXTENSIONS == (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm")
