"""What the command-line tests share: scenes written by ``evseg simulate``, and error lines."""

from evseg_torch.app.cli import main

SIZE = "90x120"


def scene_file(tmp_path, seed=0, duration_ms=40):
    """``tmp_path/scenes/scene_<seed>.npz``: a one-object synthetic scene of :data:`SIZE`."""
    assert (
        main(
            [
                "--quiet",
                "simulate",
                "--out",
                str(tmp_path / "scenes"),
                "--seeds",
                str(seed),
                "--sensor-size",
                SIZE,
                "--duration-ms",
                str(duration_ms),
                "--objects",
                "1",
            ]
        )
        == 0
    )
    return tmp_path / "scenes" / f"scene_{seed:04d}.npz"


def error_line(capsys):
    """The one line a failed command wrote on standard error, checked to be one ``evseg: error:`` line."""
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("evseg: error: ")
    return err[0]


def text_file(tmp_path, name, lines):
    """``tmp_path/name`` holding ``lines``, one a line."""
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path
