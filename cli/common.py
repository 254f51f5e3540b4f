"""What the command groups share: the help formatter, the daemon's settings from the command line,
the Zenoh transport options and the catalog table."""

from __future__ import annotations

import argparse
import socket
import textwrap

from posefuse.estimator.core.errors import PosefuseError

# Outputs that nobody asked for by path go under runs/ of the current folder, never into the
# project's own files: regenerating a committed file takes an explicit --out.
RUNS = "runs"


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Every option's help ends with its default; required options say so instead. Options
    whose default is None (or flags, False) are left as they are: their help says what happens
    when they are omitted. Descriptions keep their paragraphs (separated by a blank line)."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        return "\n\n".join(
            textwrap.fill(
                " ".join(p.split()), width, initial_indent=indent, subsequent_indent=indent
            )
            for p in text.split("\n\n")
        )

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if action.required and action.option_strings:
            return f"{text} (required)"
        if action.default is None or action.default is False:
            return text
        if isinstance(action.default, bool) or action.default is argparse.SUPPRESS:
            return text
        return super()._get_help_string(action)


def add_command(
    subparsers, name: str, help: str, description: str | None = None
) -> argparse.ArgumentParser:
    """A sub-command with the project's help formatter; its description is ``help`` (and
    ``description`` after it, when given)."""
    text = help[:1].upper() + help[1:] + "."
    if description:
        text = f"{text}\n\n{description}"
    return subparsers.add_parser(name, help=help, description=text, formatter_class=HelpFormatter)


def _settings(args: argparse.Namespace):
    """The daemon's settings: the options given on the command line over the environment
    (POSEFUSE_*), the POSEFUSE_CONFIG file and the defaults."""
    # lazy: pydantic and pydantic-settings (~0.1 s), too slow for --help
    from pydantic import ValidationError

    from posefuse.service.settings import Settings

    overrides = {}
    parts = getattr(args, "parts", None)
    if parts is not None:
        from posefuse.sim.onboard import load_part_set  # lazy: loads trimesh and scipy (~0.5 s)

        if getattr(args, "catalog", None) or getattr(args, "model", None):
            raise PosefuseError("--parts names the catalog and the model: drop --catalog/--model")
        part_set = load_part_set(parts)
        overrides.update(catalog=part_set.catalog, model=part_set.model)
    for name in ("cell", "mode", "http_host", "http_port", "catalog", "model"):
        value = getattr(args, name, None)
        if value is not None:
            overrides[name] = value
    if getattr(args, "listen", None):
        overrides["listen"] = args.listen
    if getattr(args, "connect", None):
        overrides["connect"] = args.connect
    for name in ("zenoh_config", "state_dir"):
        if getattr(args, name, None):
            overrides[name] = getattr(args, name)
    try:
        return Settings(**overrides)
    except ValidationError as exc:
        first = exc.errors()[0]
        field = ".".join(str(x) for x in first["loc"])
        raise PosefuseError(f"setting {field}: {first['msg']}") from None


def settings_default(env: str, fallback: str) -> str:
    """The help text's tail of an option that overrides one of the daemon's settings."""
    return f"default: ${env}, else the POSEFUSE_CONFIG file, else {fallback}"


def _add_transport_args(p: argparse.ArgumentParser, listen_default: str | None = None) -> None:
    """--cell, --mode, --listen and --connect; ``listen_default`` replaces the help's default of
    --listen for commands that choose their own."""
    p.add_argument(
        "--cell",
        help="key prefix of the cell: {cell}/@v1/... ("
        + settings_default("POSEFUSE_CELL", "posefuse")
        + ")",
    )
    p.add_argument(
        "--mode",
        choices=["peer", "client"],
        help="zenoh mode (" + settings_default("POSEFUSE_MODE", "peer") + ")",
    )
    p.add_argument(
        "--listen",
        nargs="+",
        metavar="ENDPOINT",
        help="zenoh listen endpoints, e.g. tcp/127.0.0.1:7447 ("
        + (listen_default or settings_default("POSEFUSE_LISTEN", "tcp/127.0.0.1:7447"))
        + ")",
    )
    p.add_argument(
        "--connect",
        nargs="+",
        metavar="ENDPOINT",
        help="zenoh endpoints to connect to, e.g. tcp/router:7447 ("
        + settings_default("POSEFUSE_CONNECT", "none")
        + ")",
    )
    p.add_argument(
        "--zenoh-config",
        metavar="FILE",
        help="a Zenoh JSON5 config file (TLS, access control), kept as is except for the "
        "transport options given explicitly ("
        + settings_default("POSEFUSE_ZENOH_CONFIG", "none")
        + ")",
    )


def _catalog_table(catalog) -> str:
    rows = ["| obj_id | name | diameter (mm) | symmetries |", "|---|---|---|---|"]
    for obj_id, model in catalog.items():
        diameter_mm = model.diameter * 1000
        symmetries = model.describe_symmetries()
        rows.append(f"| {obj_id} | {model.name} | {diameter_mm:.1f} | {symmetries} |")
    return "\n".join(rows)


def add_parts_arg(p: argparse.ArgumentParser) -> None:
    """``--parts DIR``: a part set written by ``posefuse onboard`` (its catalog and model)."""
    p.add_argument(
        "--parts",
        metavar="DIR",
        help="a part set written by `posefuse onboard` (its catalog and model; instead of "
        "--catalog and --model)",
    )


def claim_http_port(settings):
    """The settings with a usable HTTP port, checked before anything is announced: port 0 picks
    a free one; a port in use is one clear error naming it."""
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((settings.http_host, settings.http_port))
        except OSError as exc:
            raise PosefuseError(
                f"HTTP port {settings.http_host}:{settings.http_port} is not free ({exc.strerror});"
                " choose another with --http-port, or --http-port 0 for any free one"
            ) from None
        port = s.getsockname()[1]
    return settings.model_copy(update={"http_port": port})
