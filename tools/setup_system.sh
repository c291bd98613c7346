#!/usr/bin/env bash
# System pieces the project needs (Debian): PortAudio for sounddevice, jackd2 for the JACK dummy
# audio server used by the sound-card tests, iproute2 and nftables for the network-namespace test
# (tests/net/test_netns.py), openssl for the certificates of the TLS test. Installs only what is missing; needs root for apt-get.
set -euo pipefail
need=()
ldconfig -p 2>/dev/null | grep -q libportaudio.so.2 || need+=(libportaudio2)
command -v jackd >/dev/null 2>&1 || need+=(jackd2)
command -v jack_lsp >/dev/null 2>&1 || need+=(jackd2)
command -v ip >/dev/null 2>&1 || need+=(iproute2)
command -v nft >/dev/null 2>&1 || need+=(nftables)
command -v openssl >/dev/null 2>&1 || need+=(openssl)
if [ ${#need[@]} -eq 0 ]; then exit 0; fi
if [ "$(id -u)" != 0 ]; then
  echo "adhoc-array: missing system packages ${need[*]}; run: sudo apt-get install -y --no-install-recommends ${need[*]}" >&2
  exit 0   # the Python parts still work; sound-card tests skip with this reason
fi
export DEBIAN_FRONTEND=noninteractive
pkgs=$(printf '%s\n' "${need[@]}" | sort -u)
if ! { apt-get update -qq && apt-get install -y -qq --no-install-recommends $pkgs >/dev/null; }; then
  # the replay engine and its tests run without them; only sound-card use needs them
  echo "adhoc-array: could not install $pkgs with apt-get; sound-card features will say what is missing" >&2
fi
