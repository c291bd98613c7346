"""A tiny PKI for the mutual-TLS test, made with the openssl CLI.

make_certs(directory) -> dict[str, Path] with keys:
  ca_key, ca_cert                 - the trusted CA
  server_key, server_cert         - router cert (SAN IP:127.0.0.1, DNS:localhost), signed by CA
  good_key, good_cert             - client cert signed by CA
  rogue_ca_key, rogue_ca_cert     - a second, untrusted CA
  rogue_key, rogue_cert           - client cert signed by the rogue CA
All keys are EC P-256 (PKCS#8 PEM). Certs are X.509 v3, valid 30 days.
"""
from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

OPENSSL = shutil.which("openssl") or "openssl"
DAYS = "30"


def _run(*args: str) -> None:
    r = subprocess.run([OPENSSL, *args], capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"openssl {' '.join(args)} failed:\n{r.stderr}")


def _key(path: Path) -> None:
    _run("genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256",
         "-out", str(path))


def _ca(d: Path, name: str, cn: str) -> tuple[Path, Path]:
    key, cert = d / f"{name}.key", d / f"{name}.pem"
    _key(key)
    _run("req", "-x509", "-new", "-key", str(key), "-sha256", "-days", DAYS,
         "-subj", f"/CN={cn}",
         "-addext", "basicConstraints=critical,CA:TRUE",
         "-addext", "keyUsage=critical,keyCertSign,cRLSign",
         "-out", str(cert))
    return key, cert


def _leaf(d: Path, name: str, cn: str, ca_key: Path, ca_cert: Path,
          eku: str, san: str | None) -> tuple[Path, Path]:
    key, csr, cert, ext = (d / f"{name}.key", d / f"{name}.csr",
                           d / f"{name}.pem", d / f"{name}.ext")
    _key(key)
    _run("req", "-new", "-key", str(key), "-subj", f"/CN={cn}", "-out", str(csr))
    lines = ["basicConstraints=critical,CA:FALSE",
             "keyUsage=critical,digitalSignature",
             f"extendedKeyUsage={eku}"]
    if san:
        lines.append(f"subjectAltName={san}")
    ext.write_text("\n".join(lines) + "\n")
    _run("x509", "-req", "-in", str(csr), "-CA", str(ca_cert), "-CAkey", str(ca_key),
         "-CAcreateserial", "-days", DAYS, "-sha256", "-extfile", str(ext),
         "-out", str(cert))
    csr.unlink()
    ext.unlink()
    return key, cert


def make_certs(directory) -> dict[str, Path]:
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    out: dict[str, Path] = {}
    out["ca_key"], out["ca_cert"] = _ca(d, "ca", "zenoh-test-ca")
    out["server_key"], out["server_cert"] = _leaf(
        d, "server", "localhost", out["ca_key"], out["ca_cert"],
        "serverAuth", "IP:127.0.0.1,DNS:localhost")
    out["good_key"], out["good_cert"] = _leaf(
        d, "good_client", "good-device", out["ca_key"], out["ca_cert"],
        "clientAuth", None)
    out["rogue_ca_key"], out["rogue_ca_cert"] = _ca(d, "rogue_ca", "rogue-ca")
    out["rogue_key"], out["rogue_cert"] = _leaf(
        d, "rogue_client", "rogue-device", out["rogue_ca_key"], out["rogue_ca_cert"],
        "clientAuth", None)
    return out

