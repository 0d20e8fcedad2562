"""Human-facing output: the progress bar of a long run and the end-of-session summary."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager

from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from teleop_rt.analysis.transparency import transparency_labels
from teleop_rt.loop import format_percentiles
from teleop_rt.session import Summary


@contextmanager
def progress_bar(total: int, enabled: bool = True) -> Iterator[Callable[[int, int], None] | None]:
    """Yield a ``progress(done, total)`` callback drawing a bar on stderr (None if disabled)."""
    if not enabled:
        yield None
        return
    columns = (
        TextColumn("[bold]ticks"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total}"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
    )
    with Progress(*columns, console=Console(stderr=True), transient=True) as bar:
        task = bar.add_task("run", total=total)

        def update(done: int, _total: int) -> None:
            bar.update(task, completed=done)

        yield update


def speed(ratio: float) -> str:
    """Simulated over wall time as '55x', '2.4x', '0.31x' (a slow run is not '0x')."""
    if ratio >= 10:
        return f"{ratio:.0f}x"
    return f"{ratio:.2g}x" if ratio < 1 else f"{ratio:.1f}x"


def _fmt(values: list[float]) -> str:
    return "  ".join(f"{v:.4g}" for v in values)


def print_summary(summary: Summary, console: Console | None = None) -> None:
    """Print the session summary as a table."""
    console = console or Console()
    table = Table(title=f"session {summary.name}", show_header=False, title_justify="left")
    table.add_column("what", style="bold")
    table.add_column("value")
    table.add_row("ticks", f"{summary.ticks} ({summary.simulated_time_s:.3f} s simulated)")
    table.add_row("channel delay", f"{summary.delay_ticks} ticks")
    t_p_label, t_tau_label = transparency_labels(summary.space)
    table.add_row(t_p_label, _fmt(summary.t_p))
    table.add_row("T_p total", f"{summary.t_p_total:.4g}")
    table.add_row(t_tau_label, _fmt(summary.t_tau))
    table.add_row("T_tau total", f"{summary.t_tau_total:.4g}")
    table.add_row(
        "channel energy (J)",
        f"{summary.channel_energy_j:.4g} (minimum {summary.min_channel_energy_j:.3g})",
    )
    timing = summary.timing
    comp, late = timing["compute_us"], timing["lateness_us"]
    table.add_row("tick compute (us)", format_percentiles(comp))
    if summary.realtime:
        table.add_row("deadline lateness (us)", format_percentiles(late))
        table.add_row(
            "missed deadlines",
            f"{timing['missed_deadlines']} (ticks started over a period late: "
            f"{timing.get('late_over_period', 0)})",
        )
    else:
        rtf = summary.simulated_time_s / max(timing.get("wall_s", 0.0), 1e-9)
        table.add_row("mode", f"fast mode, {speed(rtf)} real time")
        note = preemption_note(comp)
        if note:
            table.add_row("note", note)
    for note in summary.notes:
        table.add_row("note", note)
    if summary.saturated_ticks:
        table.add_row("torque saturated", f"{summary.saturated_ticks} ticks (URDF effort limits)")
    tool = tool_limits_text(summary.tool_limits)
    if tool:
        table.add_row("TO tool limits", tool)
    for site, figures in (summary.dls or {}).items():
        table.add_row(f"DLS at the {site}", dls_text(figures))
    if summary.stopped_early:
        table.add_row("stopped early", f"[red]{summary.stopped_early}")
    for site, figures in (summary.link or {}).items():
        table.add_row(f"link to the {site}", _link_text({"sent": "-", "from_peer": figures}))
    if summary.channel and summary.delay_ticks:
        table.add_row("channel", channel_kind(summary.channel))
        for site in ("hsi", "to"):
            table.add_row(f"protection at the {site}", protection_text(summary.channel[site]))
        for site, figures in codec_sites(summary.channel):
            table.add_row(f"codec at the {site}", codec_text(figures))
    console.print(table)


def tool_limits_text(figures: dict | None) -> str:
    """What the TO's task-space limits did ('' when none acted)."""
    if not figures:
        return ""
    said = []
    if figures["speed_limited_ticks"]:
        said.append(f"speed limit {figures['speed_limit_m_s']:g} m/s capped the coupling for "
                    f"{figures['speed_limited_ticks']} ticks (gain down to "
                    f"{figures['min_speed_gain']:.3g})")  # fmt: skip
    if figures["wall_ticks"]:
        said.append(f"a virtual wall pushed for {figures['wall_ticks']} ticks (deepest "
                    f"{1000 * figures['max_penetration_m']:.3g} mm, "
                    f"{figures['max_wall_force_n']:.3g} N)")  # fmt: skip
    return "; ".join(said)


def dls_text(figures: dict) -> str:
    """What a site's damped least squares did: the ticks it acted on, the smallest singular
    value of the tool's Jacobian."""
    low = figures["min_singular_value"]
    return (f"active on {figures['active_ticks']} ticks (sigma_min < "
            f"{figures['active_below']:g}), min singular value "
            f"{'-' if low is None else f'{low:.3g}'}")  # fmt: skip


PREEMPTION_FACTOR = 10.0  # a max this far above p99 is the host, not the tick's own work


def preemption_note(compute_us: dict) -> str | None:
    """Why a fast run's max tick time can be milliseconds: a tick that the OS preempted
    (fast mode asks for no real-time scheduling) counts the time it did not run."""
    p99, top = compute_us.get("p99", 0.0), compute_us.get("max", 0.0)
    if not top > PREEMPTION_FACTOR * max(p99, 1e-9):
        return None
    return (
        f"max {top / 1000:.3g} ms is {top / max(p99, 1e-9):.0f} x p99: it includes host "
        "preemption (fast mode is not paced and asks for no real-time scheduling)"
    )


def channel_kind(channel: dict) -> str:
    how = f", {channel['reconstruction']} reconstruction" if "reconstruction" in channel else ""
    return f"{channel['mode']}{how}, {channel['playout']} playout"


def codec_sites(channel: dict) -> list[tuple[str, dict]]:
    """The codec's figures per site in a summary's channel (none without a codec)."""
    codec = channel.get("codec") or {}
    return [(site, codec[site]) for site in ("hsi", "to") if site in codec]


def codec_text(figures: dict) -> str:
    """A site's codec figures (``teleop_rt.com.codec.figures``) in words."""
    return (
        f"sent {figures['sent']} packets ({figures['rate_hz']:.0f} /s, "
        f"{100 * figures['reduction']:.1f} % fewer): deadband {figures['by_threshold']}, "
        f"max interval {figures['by_max_interval']}, energy room {figures['by_energy']}; "
        f"peer's silences held {figures['peer_held_ticks']} ticks, "
        f"{figures['peer_expired_ticks']} past its maximum interval (as losses)"
    )


def protection_text(figures: dict) -> str:
    """A port's protection figures (``Port.protection``) in words."""
    low = figures["min_balance_j"]
    verdict = "passive" if low >= -1e-9 else "[red]ACTIVE: made energy[/red]"
    return (
        f"balance min {low:.3g} J ({verdict}); acted in {figures['acted_ticks']} ticks, "
        f"removed {figures['removed_j']:.3g} J"
    )


def print_comparison(
    original: dict, replay: Summary, overrides: list[str], console: Console | None = None
) -> None:
    """Original log's figures and the replay's, side by side."""
    console = console or Console()
    what = ", ".join(overrides) if overrides else "no overrides"
    table = Table(title=f"replay ({what})", title_justify="left")
    table.add_column("figure", style="bold")
    table.add_column("original (log)")
    table.add_column("replay")
    rows = [
        ("ticks", str(original.get("ticks")), str(replay.ticks)),
        ("T_p per joint", _fmt(original.get("t_p", [])), _fmt(replay.t_p)),
        ("T_p total", f"{original.get('t_p_total', float('nan')):.4g}", f"{replay.t_p_total:.4g}"),
        ("T_tau per joint", _fmt(original.get("t_tau", [])), _fmt(replay.t_tau)),
        (
            "T_tau total",
            f"{original.get('t_tau_total', float('nan')):.4g}",
            f"{replay.t_tau_total:.4g}",
        ),
        (
            "channel energy (J)",
            f"{original.get('channel_energy_j', float('nan')):.4g}",
            f"{replay.channel_energy_j:.4g}",
        ),
    ]
    for row in rows:
        table.add_row(*row)
    console.print(table)


def print_site_comparison(out: dict, console: Console | None = None) -> None:
    """A site log's figures and its replay's (``teleop_rt.recording.site_replay``)."""
    console = console or Console()
    what = ", ".join(out["overrides"]) if out["overrides"] else "no overrides"
    table = Table(title=f"replay of the {out['site']} site against its partner's logged packets "
                  f"({what})", title_justify="left")  # fmt: skip
    table.add_column("figure", style="bold")
    table.add_column("original (log)")
    table.add_column("replay")
    a, b = out["original"], out["replay"]
    error = "tau_h - tau_c" if out["site"] == "hsi" else "omega_t - v_t"
    rows = [
        ("ticks", str(a["ticks"]), str(b["ticks"])),
        ("port energy (J)", f"{a['port_energy_j']:.4g}", f"{b['port_energy_j']:.4g}"),
        ("its minimum (J)", f"{a['min_port_energy_j']:.4g}", f"{b['min_port_energy_j']:.4g}"),
        (f"int ({error})^2 dt per joint", _fmt(a["controller_input"]),
         _fmt(b["controller_input"])),
        ("  total", f"{a['controller_input_total']:.4g}", f"{b['controller_input_total']:.4g}"),
        ("safety stop", "yes" if a["safety_stop"] else "no", "yes" if b["safety_stop"] else "no"),
    ]  # fmt: skip
    for row in rows:
        table.add_row(*row)
    same = "identical to the log's" if out["identical"] else "differ from the log's"
    table.add_row("signals", "", f"{same} (max |q - q_log| {out['max_abs_q_difference_rad']:.3g}"
                  " rad)")  # fmt: skip
    console.print(table)


def _link_text(link: dict) -> str:
    peer = link.get("from_peer") or {}
    delay = peer.get("delay_ticks") or {}
    lost = f"lost {peer.get('lost', 0)}"
    if "silent_ticks" in peer:  # the peer's codec: a tick with no packet is no loss
        lost += (f" packets (by their numbers; {peer['silent_ticks']} ticks with none: its "
                 "codec's silences, the losses among them)")  # fmt: skip
    return (
        f"sent {link.get('sent', 0)}; from the peer: received {peer.get('received', 0)}, used "
        f"{peer.get('used', 0)}, {lost}, late {peer.get('late', 0)}, "
        f"duplicated {peer.get('duplicated', 0)}, reordered {peer.get('reordered', 0)}, rejected "
        f"{peer.get('rejected', 0)}{_by_reason(peer.get('rejected_by_reason'))}; one-way delay "
        f"p50 {delay.get('p50')} / p99 {delay.get('p99')} / max {delay.get('max')} ticks"
    ) + _stage_text(link)


def _by_reason(counts: dict | None) -> str:
    """' (side 12, ahead 3)' for counters by reason, or ''."""
    return f" ({', '.join(f'{k} {v}' for k, v in counts.items())})" if counts else ""


def _stage_text(link: dict) -> str:
    """What a Zenoh site's impairment stage did to its packets, and its drift follower."""
    text = ""
    imp = link.get("impairment")
    if imp:
        late = link.get("send_after_due_us") or {}
        text += (
            f"; impairment here: lost {imp['lost']}, duplicated {imp['duplicated']}, reordered "
            f"{imp['reordered']}, held {imp.get('held', 0)} (out p99 {late.get('p99', 0):.0f} us "
            f"after their instant), refused {imp.get('overflow', 0)}"
        )
    hellos = link.get("hellos_ignored")
    if hellos:  # strangers' hellos during the handshake
        text += f"; invalid hellos ignored {sum(hellos.values())}{_by_reason(hellos)}"
    drift = link.get("drift")
    if drift and drift["retargets"]:
        text += (
            f"; clock drift followed: {drift['back']} zero packets, {drift['forward']} skipped "
            f"(offset {drift['offset_ticks']} ticks)"
        )
    return text


def print_site_summary(summary, console: Console | None = None) -> None:
    """One site's summary (``teleop-rt site``) as a table."""
    console = console or Console()
    table = Table(title=f"{summary.site} site of {summary.name}", show_header=False,
                  title_justify="left")  # fmt: skip
    table.add_column("what", style="bold")
    table.add_column("value")
    table.add_row("ticks", f"{summary.ticks} ({summary.simulated_time_s:g} s)")
    table.add_row("energy into the channel here", f"{summary.port_energy_j:.6g} J")
    table.add_row("channel", channel_kind(summary.channel))
    table.add_row("protection here", protection_text(summary.channel[summary.site]))
    for _, figures in codec_sites(summary.channel):
        table.add_row("codec here", codec_text(figures))
    table.add_row("link", _link_text(summary.link))
    late = summary.timing.get("lateness_us", {})
    table.add_row("deadline lateness", f"p99 {late.get('p99', 0):.1f} us, missed "
                  f"{summary.timing.get('missed_deadlines', 0)}")  # fmt: skip
    if summary.stopped_early:
        table.add_row("stopped early", summary.stopped_early)
    if summary.peer_silent:
        table.add_row("peer silent", summary.peer_silent)
    for note in summary.notes:
        table.add_row("note", note)
    if summary.log is not None:
        whole = (summary.recording or {}).get("complete")
        table.add_row("log", summary.log + ("" if whole else " (INCOMPLETE)"))
    console.print(table)


def print_pair_summary(combined: dict, console: Console | None = None) -> None:
    """Both sites of ``run --link zenoh`` and the pair's transparency, as a table."""
    console = console or Console()
    table = Table(title=f"session {combined['name']} over Zenoh (two processes)",
                  show_header=False, title_justify="left")  # fmt: skip
    table.add_column("what", style="bold")
    table.add_column("value")
    pair = combined.get("pair")
    if pair:
        table.add_row("ticks of both", str(pair["ticks"]))
        table.add_row("T_p (eq 18)", f"{pair['t_p_total']:.6g} rad^2 s")
        table.add_row("T_tau (eq 18)", f"{pair['t_tau_total']:.6g} N^2 m^2 s")
    for name, s in combined["sites"].items():
        if "error" in s:
            table.add_row(f"{name} site", f"failed: {s['error']}")
            continue
        energy = f"{s['port_energy_j']:.6g} J into the channel"
        table.add_row(f"{name} site", f"{s['ticks']} ticks; {energy}; exit "
                      f"{combined['exit_codes'][name]}")  # fmt: skip
        table.add_row(f"{name} link", _link_text(s["link"]))
        if "channel" in s:
            table.add_row(f"{name} protection", protection_text(s["channel"][name]))
            for _, figures in codec_sites(s["channel"]):
                table.add_row(f"{name} codec", codec_text(figures))
        if s.get("stopped_early"):
            table.add_row(f"{name} stopped", s["stopped_early"])
        if s.get("peer_silent"):
            table.add_row(f"{name} peer silent", s["peer_silent"])
        if s.get("log"):
            whole = (s.get("recording") or {}).get("complete")
            table.add_row(f"{name} log", s["log"] + ("" if whole else " (INCOMPLETE)"))
    console.print(table)
