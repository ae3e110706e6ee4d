"""``mvpose user add|list|disable|enable|reset|events``: the operator page's users, straight in
the store (the same settings as the server, as ``mvpose token`` uses).

A new PIN or password is asked for twice on a terminal; from a pipe it is the first line of
standard input (``echo 4711 | mvpose user add anna --role operator --pin``), so scripts never
put it on a command line where ``ps`` shows it.
"""

from __future__ import annotations

import argparse
import getpass
import sys

from server.cli import CliError
from server.commands.token import ROLES, add_store_options, open_cli_store


def add_arguments(parser: argparse.ArgumentParser) -> None:
    store = argparse.ArgumentParser(add_help=False)
    add_store_options(store)
    secret = argparse.ArgumentParser(add_help=False)
    kind = secret.add_mutually_exclusive_group(required=True)
    kind.add_argument("--pin", action="store_true",
                      help="logs in with a PIN of 4 to 8 digits (operators at a panel PC)")
    kind.add_argument("--password", action="store_true",
                      help="logs in with a password of 10 characters or more (engineers)")
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    add = sub.add_parser("add", parents=[store, secret],
                         help="add a user; the PIN or password is asked for (or read from stdin)")
    add.add_argument("name", help="user name (letters, digits, _ . -; at most 64)")
    add.add_argument("--role", required=True, choices=ROLES,
                     help="read (look only), operator (trigger, teach) or engineer (everything)")
    sub.add_parser("list", parents=[store],
                   help="every user: name, role, PIN or password, disabled, locked")
    for action, text in (("disable", "disable a user: no login, and its open pages log out"),
                         ("enable", "let a disabled user log in again"),
                         ("reset", "a new PIN or password: unlocks the user, its pages log out")):
        p = sub.add_parser(action, parents=[store, secret] if action == "reset" else [store],
                           help=text)
        p.add_argument("name")
    events = sub.add_parser("events", parents=[store],
                            help="the audit trail: logins, wrong secrets, locks, changes")
    events.add_argument("name", nargs="?", help="only this user's events")
    events.add_argument("--limit", type=int, default=50, help="newest events shown (50)")


def read_secret(word: str) -> str:
    """The new PIN or password: asked twice on a terminal, else the first line of stdin."""
    if not sys.stdin.isatty():
        line = sys.stdin.readline().rstrip("\r\n")
        if not line:
            raise CliError(f"no {word} on standard input (give it as its first line)")
        return line
    first = getpass.getpass(f"new {word}: ")
    if getpass.getpass(f"the {word} again: ") != first:
        raise CliError(f"the two {word}s differ; nothing changed")
    return first


def _table(rows: list[tuple[str, ...]]) -> None:
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    for row in rows:
        print("  ".join(v.ljust(w) for v, w in zip(row, widths, strict=True)).rstrip())


def run(args: argparse.Namespace) -> int:
    from server.auth import Role
    from server.users import NAME_PATTERN, SecretKind, add_user, reset_user

    store, where = open_cli_store(args)
    actor = "cli"
    try:
        if args.action in ("add", "reset"):
            kind = SecretKind.PIN if args.pin else SecretKind.PASSWORD
            word = "PIN" if args.pin else "password"
            if args.action == "add":
                import re

                if not re.fullmatch(NAME_PATTERN, args.name) or len(args.name) > 64:
                    raise CliError(f"user name {args.name!r}: letters, digits, _ . - only, "
                                   "at most 64")
                info = add_user(store.users, args.name, Role(args.role), kind,
                                read_secret(word), actor)
                print(f"user {info.name!r} ({info.role}, {word}) added in {where}",
                      file=sys.stderr)
            else:
                info = reset_user(store.users, args.name, kind, read_secret(word), actor)
                print(f"user {info.name!r}: new {word}; unlocked, open pages log out",
                      file=sys.stderr)
        elif args.action == "list":
            rows: list[tuple[str, ...]] = [("name", "role", "login", "created", "disabled",
                                            "locked")]
            for u in store.users.list():
                rows.append((u.name, u.role, u.secret_kind,
                             u.created_at.isoformat(timespec="seconds"),
                             u.disabled_at.isoformat(timespec="seconds") if u.disabled_at
                             else "",
                             u.locked_at.isoformat(timespec="seconds") if u.locked_at else ""))
            _table(rows)
        elif args.action == "disable":
            info = store.users.disable(args.name, actor)
            print(f"user {info.name!r} disabled; its open pages log out", file=sys.stderr)
        elif args.action == "enable":
            info = store.users.enable(args.name, actor)
            print(f"user {info.name!r} enabled", file=sys.stderr)
        else:
            trail: list[tuple[str, ...]] = [("at", "user", "event", "by", "detail")]
            for e in store.users.events(args.name, max(1, args.limit)):
                trail.append((e.at.isoformat(timespec="seconds"), e.user_name, e.event,
                              e.actor, e.detail))
            _table(trail)
    finally:
        store.close()
    return 0
