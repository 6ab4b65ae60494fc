"""Entry-point runner: bad input exits with status 2 and names the script."""

import pytest

from cvmdx_jax import cli


@pytest.mark.parametrize("error", [ValueError("bad split"), FileNotFoundError("no run")])
def test_bad_input_exits_2_with_the_message(monkeypatch, capsys, error):
  monkeypatch.setattr("sys.argv", ["/x/evaluate.py"])

  def main(argv):
    raise error
  with pytest.raises(SystemExit) as exit_info:
    cli.run(main)
  assert exit_info.value.code == 2
  assert capsys.readouterr().err == f"evaluate: error: {error}\n"


def test_other_errors_propagate(monkeypatch):
  monkeypatch.setattr("sys.argv", ["prog"])

  def main(argv):
    raise KeyError("bug")
  with pytest.raises(KeyError):
    cli.run(main)
