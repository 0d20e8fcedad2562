"""Attacks from outside, session 38: what the docs promise against what the command line and
the config schema do (every flag, every log argument, every key), and a config file that is
not a mapping. Each test drives the real parser, schema or CLI."""

from __future__ import annotations

import argparse
import re
import typing
from pathlib import Path
from types import SimpleNamespace

import pytest
from pydantic import BaseModel

from teleop_rt.cli import _build_parser, main
from teleop_rt.com import zenoh_link
from teleop_rt.com.port import HSI, Packet
from teleop_rt.config import SessionConfig
from teleop_rt.errors import SafetyStop
from tests.test_cli import assert_one_error_line

ROOT = Path(__file__).resolve().parents[1]


# --- the synopsis of every command ----------------------------------------------------------
def _synopsis(page: Path) -> dict[str, str]:
    """Each command's lines of the page's first ``teleop-rt ...`` code block, by command."""
    block = next(b for b in page.read_text().split("```")[1::2] if "teleop-rt run CONFIG" in b)
    lines: dict[str, str] = {}
    command = None
    for line in block.splitlines():
        m = re.match(r"teleop-rt (\w+)(.*)", line)
        if m:
            command, line = m.group(1), m.group(2)
        if command:
            lines[command] = lines.get(command, "") + " " + line
    return lines


def _subcommands() -> dict[str, argparse.ArgumentParser]:
    parser = _build_parser()
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


@pytest.mark.parametrize("page", ["README.md", "docs/usage.md"])
def test_the_synopsis_names_every_flag_of_each_command_and_no_other(page: str) -> None:
    synopsis = _synopsis(ROOT / page)
    commands = _subcommands()
    assert set(synopsis) == set(commands), page
    for name, sub in commands.items():
        shown = set(re.findall(r"(?<![\w-])(--?[a-z][\w-]*)", synopsis[name]))
        options = [a for a in sub._actions if a.option_strings and a.help != argparse.SUPPRESS]
        unshown = [a.option_strings for a in options
                   if not set(a.option_strings) - {"-h", "--help"} & shown
                   and "-h" not in a.option_strings]  # fmt: skip
        known = {o for a in sub._actions for o in a.option_strings}
        assert not unshown, f"{page}: teleop-rt {name}: {unshown} not in the synopsis"
        assert shown <= known, f"{page}: teleop-rt {name}: {sorted(shown - known)} unknown"


@pytest.mark.parametrize("page", ["README.md", "docs/usage.md"])
def test_a_command_that_takes_two_site_logs_says_so_in_the_synopsis(page: str) -> None:
    synopsis = _synopsis(ROOT / page)
    for name, sub in _subcommands().items():
        many = [a for a in sub._actions if not a.option_strings and a.nargs in ("+", "*")]
        assert bool(many) == ("HSI.mcap TO.mcap" in synopsis[name]), (page, name)


# --- every key of the config ------------------------------------------------------------------
# where a section's keys are described: configs.md for all, and the pages it sends a section to
PAGES_BY_SECTION = {
    "link": ("docs/configs.md", "docs/network.md"),
    "can": ("docs/can.md", "configs/can_emulated.yaml"),
}


def _models(annotation: object) -> list[type[BaseModel]]:
    found = [m for a in typing.get_args(annotation) for m in _models(a)]
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        found.append(annotation)
    return found


def _keys(model: type[BaseModel], prefix: str = "") -> list[str]:
    keys = []
    for name, field in model.model_fields.items():
        keys.append(prefix + name)
        for sub in _models(field.annotation):
            keys += _keys(sub, f"{prefix}{name}.")
    return sorted(set(keys))


def _described(leaf: str, text: str, page: str) -> bool:
    """``leaf`` is written as code in the page's prose (a span may wrap) or as a key in its YAML
    (an example file, or a fenced block of a page)."""
    key = re.compile(r"\b" + re.escape(leaf) + r":")
    if page.endswith(".yaml"):
        return bool(key.search(text))
    parts = text.split("```")
    prose, fenced = parts[0::2], parts[1::2]
    spans = [s for p in prose for s in re.findall(r"`([^`]*)`", p)]  # paired in order
    word = re.compile(r"\b" + re.escape(leaf) + r"\b")
    return any(word.search(s) for s in spans) or any(key.search(b) for b in fenced)


def test_every_config_key_is_described_where_the_docs_send_a_reader() -> None:
    missing = []
    for key in _keys(SessionConfig):
        pages = PAGES_BY_SECTION.get(key.split(".")[0], ("docs/configs.md",))
        leaf = key.rsplit(".", 1)[-1]
        if not any(_described(leaf, (ROOT / p).read_text(), p) for p in pages):
            missing.append(key)
    assert not missing, f"config keys described nowhere the docs send a reader: {missing}"


# --- a config file that is not a mapping --------------------------------------------------------
@pytest.mark.parametrize("text", ["- 1\n- 2\n", "just words\n", "42\n"])
@pytest.mark.parametrize("sets", [[], ["--set", "channel.delay_ms=10"]])
def test_a_config_that_is_not_a_mapping_is_one_line_naming_the_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str, sets: list[str]
) -> None:
    path = tmp_path / "not_a_mapping.yaml"
    path.write_text(text)
    assert main(["check", str(path), *sets]) == 2
    assert_one_error_line(capsys.readouterr().err, str(path), "expected a mapping")


# --- a site held off (SIGSTOP) ------------------------------------------------------------------
def test_a_site_held_off_longer_than_the_peer_timeout_stops_and_says_so(monkeypatch) -> None:
    """SIGSTOP of a site for 2 s, its peer's packets queued meanwhile: on SIGCONT its loop
    went on (exit 0 at TDPA with the codec, whose timeout adds a maximum interval of up to
    10 s), or stopped blaming a peer that had sent all along. Now the own gap is the stop."""
    pytest.importorskip("zenoh")
    from tests.test_zenoh_attacks import hsi_link, wire

    link = hsi_link()
    now = [10**12]
    monkeypatch.setattr(zenoh_link, "time", SimpleNamespace(monotonic_ns=lambda: now[0]))
    period, into = round(link.period_ns), Packet(2)
    try:
        link.start()
        for k in range(600):  # ticks 1 ms apart, the TO's packets on time: no stop
            link.tick[0], now[0] = k, link.start_ns + k * period
            link._arrive(wire(k), now[0])
            link.receive(HSI, into)
        k = 600 + 2000  # held off for 2 s; the TO's packet of that tick arrived first
        link.tick[0], now[0] = k, link.start_ns + k * period
        link._arrive(wire(k), now[0])
        with pytest.raises(SafetyStop, match="this site was held off for 2001 ms between two"):
            link.receive(HSI, into)
    finally:
        link.close()


# --- a Zenoh locator that the site would refuse ---------------------------------------------
@pytest.mark.parametrize(
    ("locator", "named"),
    [
        ("garbage", "not a Zenoh locator"),
        ("udp/127.0.0.1:99999", "the port must be a whole number 0..65535"),
        ("tcp/127.0.0.1", "needs HOST:PORT"),
        ("udp/127.0.0.1:x", "the port must be"),
    ],
)
def test_a_locator_the_site_would_refuse_is_refused_by_check(
    locator: str, named: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """`check` said ok to udp/127.0.0.1:99999; the site then failed to open Zenoh ('invalid
    port value'), a line naming no key."""
    code = main(["check", str(ROOT / "configs/stiff_wall.yaml"),
                 "--set", f"link.zenoh.to.connect=['{locator}']"])  # fmt: skip
    assert code == 2
    assert_one_error_line(capsys.readouterr().err, "link.zenoh.to.connect", locator, named)


@pytest.mark.parametrize(
    "locator",
    ["udp/127.0.0.1:7447", "udp/[::1]:0", "tcp/localhost:7447?iface=lo", "unixsock-stream//tmp/s"],
)
def test_a_locator_of_any_valid_form_is_accepted(locator: str) -> None:
    from teleop_rt.config import ZenohEndpoints

    assert ZenohEndpoints(connect=[locator]).connect == [locator]


# --- a deadband with the codec off ------------------------------------------------------------
@pytest.mark.parametrize(
    ("sets", "warned"),
    [
        (["channel.deadband.weber_hsi=0.3"], True),  # tuned, codec off: silently unused before
        (["channel.deadband.exchange_j=1e-4", "channel.mode=tdpa"], True),
        ([], False),
        (["channel.codec=deadband", "channel.delay_ms=10", "channel.deadband.weber_hsi=0.3"],
         False),
    ],
)
def test_a_deadband_without_the_codec_is_a_warning(
    sets: list[str], warned: bool, capsys: pytest.CaptureFixture[str]
) -> None:
    args = [a for s in sets for a in ("--set", s)]
    assert main(["check", str(ROOT / "configs/stiff_wall.yaml"), *args]) == 0
    err = capsys.readouterr().err
    assert ("warning: channel.deadband is set but not used" in err) == warned, err
