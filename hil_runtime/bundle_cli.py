"""``hil bundle keygen | sign | seal | check``: Ed25519 keys and signatures for policy bundles; every load check.

    hil bundle keygen --out keys/lab            # keys/lab.key (private, 0600) and keys/lab.pub
    hil bundle sign models/bundles/ur5_paper/pd --key keys/lab.key
    hil bundle check models/bundles/ur5_paper/pd --trusted-key keys/lab.pub
    hil bundle check models/bundles/ur5/pd --encoder-noise-rad 2e-6    # the runtime's sensing gate at this noise

The runtime config lists the public keys it trusts (``bundle.trusted_keys``); docs/security.md.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Annotated

import typer

bundle_app = typer.Typer(help="Sign and check policy bundles (docs/security.md, 'Bundles').", no_args_is_help=True)


class BundleKeyError(ValueError):
    """A key or bundle path the command cannot use: one line, exit 2."""

    exit_code = 2


def _manifest_of(bundle: Path) -> Path:
    from hil_runtime.bundle_schema import MANIFEST

    manifest = bundle / MANIFEST
    if not manifest.is_file() or manifest.is_symlink():
        raise BundleKeyError(f"{bundle}: no {MANIFEST} (not a bundle directory)")
    return manifest


@bundle_app.command()
def keygen(out: Annotated[Path, typer.Option(help="key path without suffix: writes OUT.key and OUT.pub")]) -> None:
    """A new Ed25519 key pair: OUT.key (PEM, PKCS#8, mode 0600) and OUT.pub (PEM)."""
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
    from cryptography.hazmat.primitives.serialization import (
        Encoding,
        NoEncryption,
        PrivateFormat,
        PublicFormat,
    )

    private, public = out.with_name(out.name + ".key"), out.with_name(out.name + ".pub")
    for path in (private, public):
        if path.exists():
            raise BundleKeyError(f"--out {out}: {path} exists (not overwritten)")
    key = Ed25519PrivateKey.generate()
    pem = key.private_bytes(Encoding.PEM, PrivateFormat.PKCS8, NoEncryption())
    try:
        handle = os.open(private, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except OSError as exc:
        raise BundleKeyError(f"--out {out}: cannot write {private} ({exc.strerror})") from None
    with os.fdopen(handle, "wb") as file:
        file.write(pem)
    public.write_bytes(key.public_key().public_bytes(Encoding.PEM, PublicFormat.SubjectPublicKeyInfo))
    print(f"wrote {private} (keep it private) and {public} (list it in bundle.trusted_keys)")


@bundle_app.command()
def sign(
    bundle: Annotated[Path, typer.Argument(help="the bundle directory")],
    key: Annotated[Path, typer.Option(help="Ed25519 private key (PEM, `hil bundle keygen`)")],
) -> None:
    """Sign the bundle's manifest (Ed25519 over its bundle_id); the graph and files are not changed."""
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
    from cryptography.hazmat.primitives.serialization import load_pem_private_key

    from hil_runtime.bundle import PolicyBundle
    from hil_runtime.bundle_security import sign_manifest
    from hil_runtime.outputs import write_text_atomic

    try:
        private = load_pem_private_key(key.read_bytes(), password=None)
    except (OSError, ValueError, TypeError) as exc:
        raise BundleKeyError(f"--key {key}: not an unencrypted PEM private key ({str(exc)[:80]})") from None
    if not isinstance(private, Ed25519PrivateKey):
        raise BundleKeyError(f"--key {key}: not an Ed25519 key")
    PolicyBundle.load(bundle)  # every check first: only a bundle the runtime would load is signed
    manifest = _manifest_of(bundle)
    signed = sign_manifest(json.loads(manifest.read_text()), private)
    write_text_atomic(manifest, json.dumps(signed, indent=1))
    print(f"signed {manifest} (bundle_id {signed['bundle_id'][:12]}…, key {signed['signatures'][-1]['key']})")


@bundle_app.command()
def check(
    bundle: Annotated[Path, typer.Argument(help="the bundle directory")],
    trusted_key: Annotated[list[Path] | None, typer.Option(help="a trusted public key (PEM); repeatable")] = None,
    encoder_noise_rad: Annotated[
        float | None,
        typer.Option(
            help="the arm's encoder noise, RMS, as bundle.encoder_noise_rad (the runtime's sensing gate; default: "
            "the runtime's, about one increment of a 19-bit encoder)"
        ),
    ] = None,
    velocity_noise_rad_s: Annotated[
        float | None,
        typer.Option(help="the drives' velocity noise, RMS (default: the position differenced over one period)"),
    ] = None,
    velocity_filter_hz: Annotated[
        float | None,
        typer.Option(help="the runtime's velocity input filter, as bundle.velocity_filter_hz (default: off)"),
    ] = None,
) -> None:
    """Every check the runtime makes when it loads the bundle in lmpc mode (signature too, with --trusted-key;
    the sensing gate at the stated noise: the predicted torque step per period of each joint is printed)."""
    import math

    from hil_runtime.bundle import DEFAULT_ENCODER_NOISE_RAD, PolicyBundle
    from hil_runtime.bundle_security import BundleSecurityError, load_public_key

    if encoder_noise_rad is None:
        encoder_noise_rad = DEFAULT_ENCODER_NOISE_RAD
    for flag, value in (("--encoder-noise-rad", encoder_noise_rad), ("--velocity-noise-rad-s", velocity_noise_rad_s)):
        if value is not None and not (math.isfinite(value) and value >= 0.0):
            raise BundleKeyError(f"{flag}: must be a finite RMS noise >= 0, got {value!r}")
    try:
        keys = [load_public_key(path) for path in trusted_key or []]
    except BundleSecurityError as exc:
        raise BundleKeyError(f"--trusted-key {exc}") from None
    loaded = PolicyBundle.load(bundle, trusted_keys=keys)
    if velocity_filter_hz is not None:
        from hil_runtime.velocity_filter import filter_pole

        try:
            filter_pole(velocity_filter_hz, loaded.period_s)
        except ValueError as exc:
            raise BundleKeyError(f"--velocity-filter-hz: {exc}") from None
    steps = loaded.check_sensing(encoder_noise_rad, velocity_noise_rad_s, velocity_filter_hz)
    velocity = f", {velocity_noise_rad_s:g} rad/s" if velocity_noise_rad_s is not None else ""
    filtered = f", filtered at {velocity_filter_hz:g} Hz" if velocity_filter_hz is not None else ""
    noise = f"{encoder_noise_rad:g} rad{velocity}{filtered}"
    print(
        f"{bundle}: ok (law {loaded.law_name}, {loaded.n_joints} joints{', signature verified' if keys else ''}; "
        f"noise {noise}: torque steps {', '.join(f'{v:.2f}' for v in steps)} N m per period, "
        f"bound {', '.join(f'{v:.2f}' for v in loaded.torque_rate_nm_s * loaded.period_s)})"
    )


def register(app: typer.Typer) -> None:
    app.add_typer(bundle_app, name="bundle")
