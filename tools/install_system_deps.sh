#!/usr/bin/env bash
# System libraries ringscan needs (Debian/Ubuntu package names):
#   libusb-1.0-0                 Open3D loads it at import
#   libgl1 libegl1 libgomp1      Open3D's and OpenCV's runtime libraries
#   libvulkan1 mesa-vulkan-drivers  Open3D's offscreen renderer (software Vulkan)
#   xvfb                         a virtual X server: the display projector's tests show
#                                patterns on it and read them back
# Installs the missing ones with apt-get when run as root (or with password-less
# sudo); otherwise prints the command to run.
set -u
pkgs=(libusb-1.0-0 libgl1 libegl1 libgomp1 libvulkan1 mesa-vulkan-drivers xvfb)
command -v dpkg-query >/dev/null 2>&1 || { echo "ringscan: not a Debian-like system; install the equivalents of: ${pkgs[*]}"; exit 0; }
missing=()
for p in "${pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
[ ${#missing[@]} -eq 0 ] && exit 0
echo "ringscan: installing system packages: ${missing[*]}"
if [ "$(id -u)" -eq 0 ]; then SUDO=""; elif sudo -n true 2>/dev/null; then SUDO="sudo -n"; else
  echo "ringscan: please run: sudo apt-get install -y ${missing[*]}"; exit 0; fi
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq >/dev/null 2>&1 || true
$SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null 2>&1 \
  || echo "ringscan: apt-get could not install ${missing[*]}; install them by hand"
exit 0
