#!/usr/bin/env bash
# System libraries ringscan needs (Debian/Ubuntu package names):
#   libusb-1.0-0                 Open3D loads it at import
#   libgl1 libegl1 libgomp1      Open3D's and OpenCV's runtime libraries
#   libvulkan1 mesa-vulkan-drivers  Open3D's offscreen renderer (software Vulkan)
#   xvfb                         a virtual X server: the display projector's tests show
#                                patterns on it and read them back
# and one it can do without:
#   libllvm19                    a libLLVM that Mitsuba's LLVM variant (Dr.Jit) accepts: with it
#                                `ringscan simulate --renderer mitsuba` runs vectorised (~5x faster);
#                                Dr.Jit aborts on LLVM 14-16 (Debian 12's default), so without it
#                                ringscan uses Mitsuba's scalar variant (docs/virtual_rig.md)
# Installs the missing ones with apt-get when run as root (or with password-less
# sudo); otherwise prints the command to run. The optional one is installed only where
# the package lists offer it; its absence never fails the set-up.
set -u
pkgs=(libusb-1.0-0 libgl1 libegl1 libgomp1 libvulkan1 mesa-vulkan-drivers xvfb)
optional=(libllvm19)
command -v dpkg-query >/dev/null 2>&1 || { echo "ringscan: not a Debian-like system; install the equivalents of: ${pkgs[*]} (optional: ${optional[*]})"; exit 0; }
installed() { dpkg-query -W -f='${Status}' "$1" 2>/dev/null | grep -q "install ok installed"; }
offered() { apt-cache policy "$1" 2>/dev/null | grep -q "Candidate: [0-9]"; }
missing=()
for p in "${pkgs[@]}"; do installed "$p" || missing+=("$p"); done
opt_missing=()
for p in "${optional[@]}"; do installed "$p" || opt_missing+=("$p"); done
[ ${#missing[@]} -eq 0 ] && [ ${#opt_missing[@]} -eq 0 ] && exit 0
if [ "$(id -u)" -eq 0 ]; then SUDO=""; elif sudo -n true 2>/dev/null; then SUDO="sudo -n"; else
  [ ${#missing[@]} -gt 0 ] && echo "ringscan: please run: sudo apt-get install -y ${missing[*]}"
  for p in "${opt_missing[@]}"; do
    offered "$p" && echo "ringscan: optional, for Mitsuba's fast variant: sudo apt-get install -y $p"
  done
  exit 0; fi
export DEBIAN_FRONTEND=noninteractive
if [ ${#missing[@]} -gt 0 ]; then
  echo "ringscan: installing system packages: ${missing[*]}"
  $SUDO apt-get update -qq >/dev/null 2>&1 || true
  $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null 2>&1 \
    || echo "ringscan: apt-get could not install ${missing[*]}; install them by hand"
fi
for p in "${opt_missing[@]}"; do
  if offered "$p"; then
    echo "ringscan: installing optional system package: $p"
    $SUDO apt-get install -y -qq --no-install-recommends "$p" >/dev/null 2>&1 \
      || { $SUDO apt-get update -qq >/dev/null 2>&1; $SUDO apt-get install -y -qq --no-install-recommends "$p" >/dev/null 2>&1; } \
      || echo "ringscan: apt-get could not install the optional $p; Mitsuba will run its scalar variant"
  fi
done
exit 0
