"""Bad configs: ibr.toml and --set. Paths named in configs stay inside their folder."""
import pytest
from conftest import refused


def _toml(ws, extra: str, raw: bytes | None = None):
    p = ws / "ibr.toml"
    p.write_bytes(raw if raw is not None else (p.read_text() + extra).encode())


@pytest.mark.parametrize("extra,needles", [
    ("[ingest\n", ("ibr.toml", "malformed TOML")),
    ("[nosuchstage]\nx = 1\n", ("ibr.toml", "unknown table [nosuchstage]")),
    ("[ingest]\nmin_views = -1\n", ("ibr.toml", "ingest.min_views")),
    ("[ingest]\nmin_views = 1e400\n", ("ibr.toml", "ingest.min_views")),
    ("[ingest]\nmin_views = \"many\"\n", ("ibr.toml", "ingest.min_views")),
    ("[ingest]\nno_such_field = 1\n", ("ibr.toml", "no_such_field")),
    ("[global_mesh.fusion]\nvoxel_rel = nan\n", ("ibr.toml", "global_mesh.fusion")),
    ("[view_depth]\nstrokes_dir = \"../outside\"\n", ("ibr.toml", "view_depth.strokes_dir", "climbs out")),
    ("[view_depth]\nstrokes_dir = \"/etc\"\n", ("ibr.toml", "view_depth.strokes_dir", "absolute")),
    ("[supersample.train]\nvgg_weights = \"../../vgg.pt\"\n", ("ibr.toml", "vgg_weights", "climbs out")),
])
def test_bad_toml(capsys, ws, input_dir, extra, needles):
    _toml(ws, extra)
    refused(capsys, ["run", ws], input_dir, ws, *needles)


def test_toml_not_utf8(capsys, ws, input_dir):
    _toml(ws, "", raw=(ws / "ibr.toml").read_bytes() + b"# caf\xe9\n")
    refused(capsys, ["run", ws], input_dir, ws, "ibr.toml", "UTF-8")


def test_unknown_key_in_input_table(capsys, ws, input_dir):
    text = (ws / "ibr.toml").read_text().replace("[input]\n", "[input]\ndepth_scale = 5000\n")
    (ws / "ibr.toml").write_text(text)
    refused(capsys, ["run", ws], input_dir, ws, "ibr.toml", "input.depth_scale")


def test_input_table_not_a_table_and_missing_input_folder(capsys, ws, input_dir, tmp_path):
    (ws / "ibr.toml").write_text("input = 3\n")
    refused(capsys, ["run", ws], input_dir, ws, "ibr.toml", "[input]")
    (ws / "ibr.toml").write_text(f'[input]\npath = "{tmp_path / "gone"}"\n')
    refused(capsys, ["run", ws], input_dir, ws, "gone", "does not exist")


@pytest.mark.parametrize("setting,needle", [
    ("view_depth.strokes_dir=../outside", "view_depth.strokes_dir"),
    ("view_depth.strokes_dir=/tmp", "view_depth.strokes_dir"),
    ("ingest.min_views=0", "ingest.min_views"),
    ("ingest.min_views=abc", "ingest.min_views"),
    ("ingest.check_pixels=maybe", "ingest.check_pixels"),
    ("global_mesh.fusion.nope=1", "global_mesh.fusion.nope"),
    ("nosuch.field=1", "nosuch"),
    ("ingest", "STAGE.FIELD=VALUE"),
    ("render_views.renderer.visibility=sometimes", "visibility"),
])
def test_bad_set(capsys, ws, input_dir, setting, needle):
    refused(capsys, ["run", ws, "--set", setting], input_dir, ws, needle)


@pytest.mark.parametrize("argv,needle", [
    (["ingest", "{ws}", "--min-views", "0"], "ingest.min_views"),
    (["ingest", "{ws}", "--check-pixels", "maybe"], "ingest.check_pixels: expected true/false"),
    (["run", "{ws}", "--set", "ingest.min_views=99"], "4 image(s) found, ingest.min_views is 99"),
])
def test_bad_stage_flags_and_values_checked_in_the_stage(capsys, ws, input_dir, argv, needle):
    refused(capsys, [a.format(ws=ws) for a in argv], input_dir, ws, needle)


@pytest.mark.parametrize("flags,needle", [
    (["--jobs", "0"], "--jobs"), (["--dask-local", "-1"], "--dask-local"),
    (["--dask-timeout", "0"], "--dask-timeout"), (["--from", "nosuch"], "nosuch"),
    (["--from", "evaluate", "--until", "ingest"], "comes after"),
])
def test_bad_flags(capsys, ws, input_dir, flags, needle):
    refused(capsys, ["run", ws, *flags], input_dir, ws, needle)


def test_workspace_keys_cannot_escape(ws, input_dir):
    """The resolver every key goes through: scene.json or a config naming `input/../x` or an
    absolute path is refused, never read."""
    from ibr_pipeline.errors import InputError
    from ibr_pipeline.workspace import Workspace
    w = Workspace(ws)
    assert w.path("input/images/1.png") == input_dir / "images" / "1.png"
    assert w.path("input/./images/../images/1.png") == input_dir / "images" / "1.png"
    for key in ("input/../outside.png", "input//etc/passwd", "../x", "/etc/passwd", "views/../../x"):
        with pytest.raises(InputError, match="climbs out|absolute"):
            w.path(key)
