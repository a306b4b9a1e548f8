#!/usr/bin/env bash
# Install the system libraries ibr_pipeline needs, when they are missing (Debian/Ubuntu).
#   EGL for headless moderngl rendering: libegl1 libegl-mesa0 libgl1-mesa-dri libgbm1
#   open3d: libusb-1.0-0
#   report test (headless browser screenshot of `ibr report`): chromium-headless-shell
set -euo pipefail
pkgs=(libegl1 libegl-mesa0 libgl1-mesa-dri libgbm1 libusb-1.0-0 chromium-headless-shell fonts-dejavu-core)
missing=()
if ! command -v dpkg-query >/dev/null 2>&1; then
  echo "install_system_deps: not a Debian/Ubuntu system; make sure these are installed: ${pkgs[*]}" >&2
  exit 0
fi
for p in "${pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -eq 0 ]; then
  echo "system libraries: all present (${pkgs[*]})"
  exit 0
fi
echo "system libraries missing: ${missing[*]}; installing with apt-get"
sudo_cmd=""
if [ "$(id -u)" -ne 0 ]; then
  command -v sudo >/dev/null 2>&1 || { echo "need root (or sudo) to apt-get install ${missing[*]}" >&2; exit 1; }
  sudo_cmd="sudo"
fi
export DEBIAN_FRONTEND=noninteractive
$sudo_cmd apt-get update -qq
$sudo_cmd apt-get install -y -qq --no-install-recommends "${missing[@]}"
