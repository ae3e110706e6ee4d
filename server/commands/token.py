"""``mvpose token create|list|revoke``: API tokens straight in the store, for the first start.

It opens the store the server uses, from the same settings (``--data-dir`` / ``MVPOSE_DATA_DIR``,
``MVPOSE_DATABASE_URL``, ``--station`` / ``MVPOSE_STATION`` for the station's name), so the
first engineer token can be made without ``MVPOSE_BOOTSTRAP_TOKEN``. A new token's secret goes
to standard output alone, once (``TOKEN=$(mvpose token create mes --role read)``); everything
else goes to standard error.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from server.cli import CliError, load_station_file

ROLES = ("read", "operator", "engineer")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    # The store options belong to each action, so they go anywhere after it:
    # `mvpose token create NAME --role engineer --data-dir /srv/mvpose`.
    store = argparse.ArgumentParser(add_help=False)
    add_store_options(store)
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    create = sub.add_parser("create", parents=[store],
                            help="create a token and print its secret once")
    create.add_argument("name", help="token name (letters, digits, _ . -; at most 64)")
    create.add_argument("--role", required=True, choices=ROLES,
                        help="read (MES), operator (trigger, teach) or engineer (everything)")
    sub.add_parser("list", parents=[store],
                   help="every token: name, role, created, revoked (never secrets)")
    revoke = sub.add_parser("revoke", parents=[store],
                            help="revoke a token (not the last live engineer token)")
    revoke.add_argument("name")


def add_store_options(parser: argparse.ArgumentParser) -> None:
    """The options that find the server's store (``mvpose token`` and ``mvpose user``)."""
    parser.add_argument("--station", type=Path,
                        help="station YAML file, for the station's name in a shared database "
                        "(default: $MVPOSE_STATION; tokens and users are not per station)")
    parser.add_argument("--data-dir", type=Path,
                        help="the server's data directory (default: $MVPOSE_DATA_DIR or ./var)")
    parser.add_argument("--database-url",
                        help="SQLAlchemy URL (default: $MVPOSE_DATABASE_URL, else the SQLite "
                        "database in the data directory)")


def open_cli_store(args: argparse.Namespace) -> tuple[Any, str]:
    """The store the server uses, from the options and the environment; and its URL."""
    from server.store import open_store

    settings = _settings(args)
    name = load_station_file(settings.station).name if settings.station else \
        settings.station_name
    url = settings.resolved_database_url
    return open_store(url, name, settings.sqlite_synchronous), url


def _settings(args: argparse.Namespace) -> Any:
    from pydantic import ValidationError

    from server.settings import Settings

    overrides: dict[str, object] = {}
    for key in ("station", "data_dir", "database_url"):
        if getattr(args, key) is not None:
            overrides[key] = getattr(args, key)
    try:
        return Settings(**overrides)  # type: ignore[arg-type]
    except ValidationError as err:
        first = err.errors()[0]
        raise CliError(f"settings: MVPOSE_{str(first['loc'][0]).upper()}: {first['msg']} "
                       f"(value: {first.get('input')!r})") from None


def run(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from server.auth import Role, create_token

    store, url = open_cli_store(args)
    try:
        if args.action == "create":
            from server.api.tokens import TokenRequest

            try:
                TokenRequest(name=args.name, role=Role(args.role))
            except ValidationError as err:
                raise CliError(f"token name {args.name!r}: {err.errors()[0]['msg']}") from None
            secret, info = create_token(store.tokens, args.name, Role(args.role))
            print(f"token {info.name!r} ({info.role}) created in "
                  f"{url}; its secret follows, shown only now:",
                  file=sys.stderr)
            print(secret, flush=True)
        elif args.action == "list":
            rows = [(t.name, t.role, t.created_at.isoformat(timespec="seconds"),
                     t.revoked_at.isoformat(timespec="seconds") if t.revoked_at else "")
                    for t in store.tokens.list()]
            widths = [max(len(r[i]) for r in [("name", "role", "created", "revoked"), *rows])
                      for i in range(4)]
            for row in [("name", "role", "created", "revoked"), *rows]:
                print("  ".join(v.ljust(w) for v, w in zip(row, widths, strict=True)).rstrip())
        else:
            info = store.tokens.revoke(args.name)
            assert info.revoked_at is not None
            print(f"token {info.name!r} ({info.role}) revoked at "
                  f"{info.revoked_at.isoformat(timespec='seconds')}", file=sys.stderr)
    finally:
        store.close()
    return 0
