"""The client-side security options shared by `pvt submit` and `pvt jobs --connect` (not a subcommand).

    pvt submit JOB --connect tls/127.0.0.1:7447 --ca certs/ca.pem --cert certs/operator.pem \
        --key certs/operator.key [--user NAME --password-file FILE]

See docs/security.md: the CA verifies the service, the certificate and key identify this client
(mutual TLS; its common name decides the role), the login is needed when the service has a users file.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any


def add_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("security (a service with [security]; docs/security.md)")
    g.add_argument("--ca", type=Path, default=None, help="CA certificate (PEM) that signed the service's certificate")
    g.add_argument("--cert", type=Path, default=None, help="this client's certificate (PEM), for mutual TLS")
    g.add_argument("--key", type=Path, default=None, help="this client's private key (PEM)")
    g.add_argument("--user", default=None, help="login name, when the service asks for one")
    g.add_argument("--password-file", type=Path, default=None, help="file holding the login's password")


def client_security(args: argparse.Namespace) -> Any:
    """A `ClientSecurity` from the options, None when none is given; raises SecurityError."""
    from streamer.api.security import SECURITY_FILE, ClientSecurity, SecurityError

    if not any((args.ca, args.cert, args.key, args.user, args.password_file)):
        return None
    password = None
    if args.password_file is not None:
        try:
            password = args.password_file.read_text(encoding="utf-8").strip()
        except OSError as exc:
            raise SecurityError(SECURITY_FILE, f"--password-file {str(args.password_file)!r}: {exc}") from None
    return ClientSecurity(
        ca=args.ca, certificate=args.cert, private_key=args.key, user=args.user, password=password
    )
