"""`pvt certs init DIR`: a CA and certificates for a service, an operator and an observer.

    pvt certs init certs/                       # ca.pem/.key, service, operator, observer .pem/.key
    pvt certs init certs/ --host 192.168.1.20   # also valid when the service is dialled at that address
    pvt certs init certs/ --identity robot=pvt-robot    # one more client certificate (CN pvt-robot)

For tests and first setups on this machine (docs/security.md says how to use your own CA). Prints the
`[security]` section that uses the files, for the cell config.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = sub.add_parser(
        "certs",
        help="make a CA and TLS certificates for a secured service and its clients",
        description="Make a CA and TLS certificates (service, operator, observer) for [security].",
    )
    verbs = p.add_subparsers(dest="certs_command", metavar="VERB")
    verbs.required = True
    init = verbs.add_parser("init", help="make ca, service, operator and observer certificates in DIR")
    init.add_argument("dir", type=Path, help="directory to write ca.pem, ca.key, <name>.pem, <name>.key to")
    init.add_argument("--days", type=int, default=825, help="validity in days (default 825)")
    init.add_argument(
        "--host",
        action="append",
        default=[],
        metavar="IP_OR_NAME",
        help="another address the service is reached at (127.0.0.1, ::1 and localhost are always in)",
    )
    init.add_argument(
        "--identity",
        action="append",
        default=[],
        metavar="NAME=CN",
        help="one more certificate: file stem NAME, common name CN (repeatable)",
    )
    init.add_argument("--force", action="store_true", help="replace existing files")
    init.set_defaults(func=run_init)
    return p


def run_init(args: argparse.Namespace) -> int:
    from streamer.api.certs import DEFAULT_IDENTITIES, CertError, init_certs

    identities = dict(DEFAULT_IDENTITIES)
    for item in args.identity:
        stem, sep, cn = item.partition("=")
        if not sep or not stem or not cn:
            print(f"pvt certs: --identity takes NAME=CN, got {item!r}", file=sys.stderr)
            return 2
        identities[stem] = cn
    try:
        made = init_certs(args.dir, identities=identities, hosts=args.host, days=args.days, force=args.force)
    except CertError as exc:
        print(f"pvt certs: {exc.code}: {exc.message}", file=sys.stderr)
        return 2
    print(f"CA        {made.ca_certificate}  (its key {made.ca_private_key} signs new certificates: keep it safe)")
    for ident in made.identities.values():
        print(f"{ident.name:<9} {ident.certificate}  key {ident.private_key}  CN {ident.common_name}")
    service = made["service"]
    print(
        "\n# for the cell config; relative paths are relative to the config file (docs/security.md)\n"
        "[security]\n"
        "enabled = true\n"
        f'ca = "{made.ca_certificate}"\n'
        f'certificate = "{service.certificate}"\n'
        f'private_key = "{service.private_key}"\n'
        "mtls = true\n"
        f'operator = ["cn:{made["operator"].common_name}"]\n'
        f'observer = ["cn:{made["observer"].common_name}"]\n'
        f'service = ["cn:{service.common_name}"]'
    )
    for stem, ident in made.identities.items():
        if stem not in DEFAULT_IDENTITIES:
            print(f'# give "cn:{ident.common_name}" ({stem}) the role it needs: operator or observer')
    return 0
