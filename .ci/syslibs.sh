#!/usr/bin/env bash
# Install the system libraries reflab's dependencies load at run time, or say how to.
set -u
missing=()
for pkg in "$@"; do
  if command -v dpkg-query >/dev/null 2>&1 && dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "ok installed"; then
    continue
  fi
  missing+=("$pkg")
done
[ ${#missing[@]} -eq 0 ] && exit 0
if command -v apt-get >/dev/null 2>&1; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  echo "installing system libraries: ${missing[*]}"
  $SUDO apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${missing[@]}" >/dev/null && exit 0
  echo "error: apt-get could not install ${missing[*]}" >&2
  exit 1
fi
cat >&2 <<MSG
warning: no apt-get here; install these by hand before running reflab:
  - LLVM >= 16 shared library (libLLVM.so; Debian/Ubuntu package libllvm19), for Mitsuba's llvm variant.
    Point DRJIT_LIBLLVM_PATH at it if it is not found by itself.
  - libusb-1.0 (Debian/Ubuntu package libusb-1.0-0), which Open3D loads.
  - for the window (reflab gui) on an X server, the xcb libraries Qt's xcb plugin links: xcb-cursor,
    xcb-icccm, xcb-keysyms, xcb-image, xcb-randr, xcb-render-util, xcb-shape, xcb-xkb, xkbcommon-x11
    (Fedora: xcb-util-cursor xcb-util-wm xcb-util-keysyms xcb-util-image xcb-util-renderutil
    libxkbcommon-x11; Arch: xcb-util-cursor xcb-util-wm xcb-util-keysyms ...). QT_DEBUG_PLUGINS=1
    reflab gui names the one missing. Xvfb (xorg-x11-server-Xvfb) for the test that opens the window.
MSG
exit 0
