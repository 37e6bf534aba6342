#!/usr/bin/env bash
# Install kestimator on a Klipper host as Moonraker's klipper_estimator, and let
# Moonraker's update manager (Mainsail's/Fluidd's update panel) keep it current.
# Run it as Moonraker's user from the checkout: ./install.sh   (./install.sh -h)
#
# Moonraker reads the system packages an update needs from this line:
# shellcheck disable=SC2034  # read by Moonraker's update manager, not here
PKGLIST="gcc python3-dev python3-venv"

set -euo pipefail

REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd -P)
VENV="$REPO/.venv-host"
LAUNCHER="$REPO/plugins/moonraker/klipper_estimator"
DATA="$HOME/printer_data"
KLIPPER_DIR="$HOME/klipper"
MODULE="$REPO/plugins/klipper/kestimator"
BUILDER="$REPO/plugins/moonraker/build-venv"
HOOK_MARK="# kestimator: build the new commit (install.sh wrote this hook)"
YES=0
UNINSTALL=0
ALLOW_ROOT=0
RESTART=1
FRONTEND_SETTINGS=0
MOONRAKER_URL="http://127.0.0.1:7125"
MOONRAKER_GIVEN=0
SETTINGS_TOOL="$REPO/plugins/klipper/frontend_settings.py"
STATE_NAME="kestimator-install.state"

usage() {
    cat <<EOF
Usage: ./install.sh [-d DIR] [-k DIR] [-y] [--no-restart] [--allow-root]
                    [--frontend-settings [--moonraker URL]]
       ./install.sh --uninstall [-d DIR] [-k DIR] [-y] [--no-restart] [--allow-root]
                    [--moonraker URL]

Installs kestimator in its own virtualenv ($VENV), compiled
when gcc and Python's headers are there, and makes Moonraker's [analysis] run it
in place of klipper_estimator; adds [analysis] and [update_manager kestimator]
to moonraker.conf (once, after a dated backup) and writes kestimator's profile
naming the printer.cfg. Where Klipper is, it links kestimator's Klipper module
into klippy/extras/ (a [kestimator] section in printer.cfg turns it on).
Run it again after any change: it changes nothing twice.

  -d DIR         Moonraker's data folder (default: ~/printer_data)
  -k DIR         Klipper's checkout (default: ~/klipper)
  -y             answer yes: install missing apt packages (sudo apt-get), restart Moonraker;
                 with --uninstall, comment out printer.cfg's [kestimator] section
  --uninstall    undo: klipper_estimator back, moonraker.conf as it was before, nothing
                 of kestimator's left but its checkout
  --no-restart   never restart Moonraker
  --allow-root   run as root (only if Moonraker itself runs as root)
  --frontend-settings
                 set Mainsail's progress, estimate and ETA settings (and Fluidd's
                 progress) so they show the Klipper module's time, through
                 Moonraker's database API; --uninstall puts back what was there
                 (it needs Moonraker running, and stops before changing anything
                 when it is not)
  --moonraker URL  Moonraker's address for that (default: http://127.0.0.1:7125;
                 --uninstall uses the one --frontend-settings last used)
  -h, --help     this text

KESTIMATOR_BUILD=pure installs the pure-Python build without trying to compile.
EOF
}

say() { printf '%s\n' "$*"; }
# $1 as one sh word: in single quotes, each ' written as '\''.
sh_quote() { printf "'%s'" "${1//\'/\'\\\'\'}"; }
die() { printf 'install.sh: %s\n' "$*" >&2; exit 1; }

while [ $# -gt 0 ]; do
    case "$1" in
        -d) [ $# -ge 2 ] || die "-d needs a folder"; DATA="$2"; shift ;;
        -k) [ $# -ge 2 ] || die "-k needs a folder"; KLIPPER_DIR="$2"; shift ;;
        -y|--yes) YES=1 ;;
        --uninstall) UNINSTALL=1 ;;
        --allow-root) ALLOW_ROOT=1 ;;
        --no-restart) RESTART=0 ;;
        --frontend-settings) FRONTEND_SETTINGS=1 ;;
        --moonraker) [ $# -ge 2 ] || die "--moonraker needs a URL"; MOONRAKER_URL="$2"
                     MOONRAKER_GIVEN=1; shift ;;
        -h|--help) usage; exit 0 ;;
        *) usage >&2; die "unknown option: $1" ;;
    esac
    shift
done

if [ "$(id -u)" = 0 ] && [ "$ALLOW_ROOT" = 0 ]; then
    die "refusing to run as root: Moonraker runs as your user (usually pi), and the
virtualenv, the link Moonraker runs and kestimator's profile must be that user's.
Run ./install.sh as Moonraker's user (it uses sudo only for apt-get), or add
--allow-root if Moonraker itself runs as root."
fi

# pip cannot build or run a checkout whose path holds one of " $ ` \ (setuptools takes
# '$name' for a variable; pip's scripts start through sh, in double quotes, when the path
# is long or has a space), and neither could an update: refused before anything changes.
case "$REPO" in
    *[\"\$\`\\]*) [ "$UNINSTALL" = 1 ] || die "the checkout's path $REPO holds one of \" \$ \` \\, which pip cannot build or run from: move (or clone) it to a folder without them, then run install.sh there. Nothing was changed." ;;
esac
[ -d "$DATA" ] || die "no Moonraker data folder at $DATA (give it with -d DIR)"
DATA=$(cd "$DATA" && pwd -P)
CONF="$DATA/config/moonraker.conf"
[ -f "$CONF" ] || die "no $CONF: is $DATA Moonraker's data folder? (-d DIR)"
TOOLS="$DATA/tools/klipper_estimator"
STATE="$TOOLS/$STATE_NAME"
PRINTER_CFG="$DATA/config/printer.cfg"
PROFILE="${XDG_CONFIG_HOME:-$HOME/.config}/kestimator/config.toml"
case "$MOONRAKER_URL" in
    *$'\n'*|*$'\r'*) die "--moonraker: the URL has a line break in it" ;;
esac
# The Moonraker --frontend-settings last used (its settings are put back through it).
if [ "$MOONRAKER_GIVEN" = 0 ] && [ -f "$STATE" ]; then
    recorded=$(sed -n 's/^moonraker_url=//p' "$STATE" | tail -n 1)
    [ -z "$recorded" ] || MOONRAKER_URL=$recorded
fi
command -v python3 >/dev/null || die "python3 is missing (sudo apt-get install python3)"

as_root() {
    if [ "$(id -u)" = 0 ]; then "$@"; else sudo "$@"; fi
}

# Moonraker's name for this machine's klipper_estimator (analysis.py, 'platform').
platform() {
    case "$(uname -m)" in
        x86_64) echo linux ;;
        armv7l|aarch64) echo rpi ;;
        *) echo "" ;;
    esac
}

# Edits moonraker.conf, keeping every byte it did not add (its line endings too) and
# editing through a symbolic link where it points (python3: configparser, as Moonraker
# reads it). Prints what it did, one line each.
conf_tool() {
    python3 - "$@" <<'PYTHON'
import configparser, os, sys
action, conf = sys.argv[1], sys.argv[2]
BEGIN = b"# >>> kestimator (install.sh; ./install.sh --uninstall removes this block)"
END = b"# <<< kestimator"
data = open(conf, "rb").read()
eol = b"\r\n" if b"\r\n" in data else b"\n"
if action == "sections":
    parser = configparser.ConfigParser(strict=False, interpolation=None)
    parser.read_string(data.decode("utf-8"))
    for name in parser.sections():
        print(name)
    if parser.has_section("analysis"):
        for key in ("platform", "estimator_config", "enable_auto_analysis",
                    "enable_estimator_updates"):
            if parser.has_option("analysis", key):
                print("analysis.%s=%s" % (key, parser.get("analysis", key).strip()))
elif action == "has-block":
    sys.exit(0 if BEGIN in data else 1)
elif action == "add":
    block = sys.argv[3].encode("utf-8").replace(b"\n", eol)
    if BEGIN in data:
        sys.exit(0)
    with open(conf, "ab") as f:
        f.write(eol + BEGIN + eol + block + END + eol)
    print("added")
elif action == "remove":
    start = data.find(eol + BEGIN + eol)
    if start < 0:
        sys.exit(0)
    end = data.find(eol + END + eol, start)
    if end < 0:
        sys.exit("moonraker.conf: %r without %r: remove kestimator's lines by hand"
                 % (BEGIN.decode(), END.decode()))
    data = data[:start] + data[end + len(END) + 2 * len(eol):]
    real = os.path.realpath(conf)
    before = os.stat(real)
    with open(real + ".kestimator-tmp", "wb") as f:
        f.write(data)
    os.chmod(real + ".kestimator-tmp", before.st_mode & 0o7777)
    if os.geteuid() == 0:
        os.chown(real + ".kestimator-tmp", before.st_uid, before.st_gid)
    os.replace(real + ".kestimator-tmp", real)
    print("removed")
PYTHON
}

# The systemd unit of this data folder's Moonraker or Klipper ($1): KIAUH names the units of
# a host's further instances moonraker-<name>.service, each reading <data>/systemd/*.env.
SYSTEMD_DIR="${KESTIMATOR_SYSTEMD_DIR:-/etc/systemd/system}"
service_name() {
    local unit
    for unit in "$SYSTEMD_DIR/$1.service" "$SYSTEMD_DIR/$1"-*.service; do
        if [ -f "$unit" ] && grep -qF "$DATA/" "$unit"; then
            basename "$unit" .service
            return
        fi
    done
    printf '%s\n' "$1"
}

# $1: what is now installed or removed, said when Moonraker is not restarted.
restart_moonraker() {
    local done_what=$1 service answer=n reason
    service=$(service_name moonraker)
    if [ "$RESTART" = 0 ]; then
        say "Moonraker not restarted (--no-restart): sudo systemctl restart $service"
        return
    fi
    if [ "$YES" = 1 ]; then
        answer=y
    elif [ -t 0 ]; then
        read -r -p "Restart Moonraker now (sudo systemctl restart $service)? [y/N] " answer
    fi
    case "$answer" in
        y|Y|yes) ;;
        *) say "Moonraker not restarted: run sudo systemctl restart $service"; return ;;
    esac
    if ! command -v systemctl >/dev/null; then
        reason="this host has no systemctl"
    elif reason=$(as_root systemctl restart "$service" 2>&1); then
        say "Moonraker restarted ($service)."
        return
    fi
    reason=$(printf '%s' "${reason:-systemctl failed}" | head -n 1)
    say "WARNING: Moonraker was not restarted (systemctl restart $service: $reason)."
    say "$done_what Restart Moonraker yourself for it to take effect (sudo systemctl restart $service, or however this host starts Moonraker)."
}

# moonraker.conf can be changed: its file (where a link points) and folders are writable,
# and the file is not read-only even for root.
conf_writable() {
    local real
    real=$(readlink -f "$CONF")
    [ -w "$real" ] && [ -w "$(dirname "$real")" ] && [ -w "$(dirname "$CONF")" ] \
        && [ "$(stat -c %A "$real" | cut -c 3)" = w ]
}

state_has() { [ -f "$STATE" ] && grep -qxF "$1" "$STATE"; }
state_add() { state_has "$1" || printf '%s\n' "$1" >> "$STATE"; }

# The Klipper module: klippy/extras/kestimator, a link to this checkout's package (as
# Klipper add-ons install; Klipper loads extras/kestimator/__init__.py), kept out of
# Klipper's git status so its updates stay clean. Before it was a package it was one file,
# linked as klippy/extras/kestimator.py: build-venv (install.sh's first step, and git's
# hook after an update from Moonraker's panel) moves that link to the package's.
EXTRAS="$KLIPPER_DIR/klippy/extras"
MODULE_LINK="$EXTRAS/kestimator"
EXCLUDE="$KLIPPER_DIR/.git/info/exclude"
EXCLUDE_LINE="klippy/extras/kestimator"
OLD_MODULE="$REPO/plugins/klipper/kestimator.py"
OLD_MODULE_LINK="$EXTRAS/kestimator.py"
OLD_EXCLUDE_LINE="klippy/extras/kestimator.py"
# $1 is our link to $2, or nothing is there.
ours_or_none() {
    { [ -L "$1" ] && [ "$(readlink "$1")" = "$2" ]; } || { [ ! -e "$1" ] && [ ! -L "$1" ]; }
}
link_module() {
    if [ ! -d "$EXTRAS" ]; then
        say "no Klipper at $KLIPPER_DIR (-k DIR): the Klipper module is not linked."
        return
    fi
    if [ -L "$MODULE_LINK" ] && [ "$(readlink "$MODULE_LINK")" = "$MODULE" ]; then
        :
    elif [ -e "$MODULE_LINK" ] || [ -L "$MODULE_LINK" ]; then
        say "WARNING: $MODULE_LINK exists and is not kestimator's link: left alone."
        return
    elif ! ours_or_none "$OLD_MODULE_LINK" "$OLD_MODULE"; then
        say "WARNING: $OLD_MODULE_LINK exists and is not kestimator's link: the Klipper module is not linked (that file is someone else's [kestimator] module)."
        return
    else
        ln -s "$MODULE" "$MODULE_LINK"
        # Our link to the module's earlier shape, if build-venv could not move it.
        rm -f "$OLD_MODULE_LINK" "$EXTRAS/__pycache__/kestimator."*.pyc
        say "Klipper module linked: $MODULE_LINK"
    fi
    if [ -d "$KLIPPER_DIR/.git/info" ] && ! grep -qx "$EXCLUDE_LINE" "$EXCLUDE" 2>/dev/null; then
        [ -e "$EXCLUDE" ] || state_add exclude_created
        if [ -s "$EXCLUDE" ] && [ -n "$(tail -c 1 "$EXCLUDE")" ]; then
            # The user's last pattern has no newline: ours goes on a line of its own.
            printf '\n' >> "$EXCLUDE"
            state_add exclude_newline
        fi
        printf '%s\n' "$EXCLUDE_LINE" >> "$EXCLUDE"
    fi
    say "To turn it on, add a [kestimator] section to printer.cfg and restart Klipper (see plugins/klipper/README.md)."
}
unlink_module() {
    local link target line
    # Whichever shape is there: the package's link, or the file's (an update not yet
    # built); only ours.
    for link in "$MODULE_LINK" "$OLD_MODULE_LINK"; do
        target=$MODULE
        [ "$link" = "$MODULE_LINK" ] || target=$OLD_MODULE
        if [ -L "$link" ] && [ "$(readlink "$link")" = "$target" ]; then
            rm -f "$link"
            # What Klipper's Python compiled of the file (Klipper's own .pyc files stay;
            # the package's are in this checkout).
            rm -f "$EXTRAS/__pycache__/kestimator."*.pyc
            say "Klipper module link removed: restart Klipper when it is not printing (sudo systemctl restart $(service_name klipper)) to unload it."
        fi
    done
    for line in "$EXCLUDE_LINE" "$OLD_EXCLUDE_LINE"; do
        unexclude "$line"
    done
}
# Our line $1 out of Klipper's .git/info/exclude (the file too when install.sh made it and
# nothing else is in it).
unexclude() {
    if [ -f "$EXCLUDE" ] && grep -qxF "$1" "$EXCLUDE"; then
        # Our line out of Klipper's .git/info/exclude, with the newline we put before it.
        local newline_added=0
        if state_has exclude_newline; then newline_added=1; fi
        python3 - "$EXCLUDE" "$1" "$newline_added" <<'PYTHON'
import os, sys
path, line, newline_added = sys.argv[1], sys.argv[2].encode() + b"\n", sys.argv[3] == "1"
data = open(path, "rb").read()
lines = data.splitlines(keepends=True)
kept = [item for item in lines if item != line]
data = b"".join(kept)
if newline_added and len(kept) < len(lines) and lines[-1] == line and data.endswith(b"\n"):
    data = data[:-1]
with open(path, "wb") as f:
    f.write(data)
PYTHON
        if state_has exclude_created && [ ! -s "$EXCLUDE" ]; then
            rm -f "$EXCLUDE"
        fi
    fi
}

# Mainsail's and Fluidd's settings, through Moonraker's database API (never their files).
# Putting them back (--undo) comes before anything else --uninstall changes: without
# Moonraker it stops there, keeping all it needs to put them back on a later --uninstall.
frontend_settings() {
    if python3 "$SETTINGS_TOOL" --moonraker "$MOONRAKER_URL" "$@"; then
        return 0
    fi
    if [ "${1:-}" = --undo ]; then
        die "Mainsail's and Fluidd's settings are not put back yet: Moonraker at $MOONRAKER_URL did not answer (see above). Start Moonraker (or give its address with --moonraker URL), then run --uninstall again. Nothing was changed."
    fi
    say "WARNING: Mainsail's and Fluidd's settings were not changed (Moonraker at $MOONRAKER_URL: see above); run again with --frontend-settings when Moonraker runs."
}

SECTION_TOOL="$REPO/plugins/klipper/config_section.py"
# Klipper does not start with a [kestimator] section and no module: before anything is
# changed, the section (in printer.cfg or a file it includes) is commented out with the
# user's yes (-y, or asked), else the uninstall stops and says what to do.
klipper_section_consent() {
    local found answer=n
    # Only for this Klipper with our link (either shape), or with none (an earlier
    # uninstall removed it): another kestimator or kestimator.py there is someone else's.
    if [ ! -d "$EXTRAS" ] || [ ! -f "$PRINTER_CFG" ] \
        || ! ours_or_none "$MODULE_LINK" "$MODULE" \
        || ! ours_or_none "$OLD_MODULE_LINK" "$OLD_MODULE"; then
        return 0
    fi
    found=$(python3 "$SECTION_TOOL" find "$PRINTER_CFG" 2>&1) \
        || die "$found (Klipper reads it so: fix it, then run --uninstall again)"
    [ -n "$found" ] || return 0
    if [ "$YES" = 1 ]; then
        answer=y
    elif [ -t 0 ]; then
        say "Klipper does not start with a [kestimator] section and no module: $(tr '\n' ' ' <<<"$found")"
        read -r -p "Comment out that section ('#' before its lines, nothing else changes)? [y/N] " answer
    fi
    case "$answer" in
        y|Y|yes) COMMENT_SECTION=1 ;;
        *) die "[kestimator] is in $(tr '\n' ' ' <<<"$found")and Klipper does not start with it once the module is gone: remove the section (or run ./install.sh --uninstall -y, which comments it out), then run --uninstall again. Nothing was changed." ;;
    esac
}
COMMENT_SECTION=0

uninstall() {
    local p link
    klipper_section_consent
    if [ -f "$CONF" ] && conf_tool has-block "$CONF" && ! conf_writable; then
        die "cannot write $CONF (or its folder): make it writable, then run --uninstall again. Nothing was changed."
    fi
    if state_has frontend_settings; then
        frontend_settings --undo
    fi
    if [ "$COMMENT_SECTION" = 1 ]; then
        local commented
        commented=$(python3 "$SECTION_TOOL" comment "$PRINTER_CFG" 2>&1) || die "$commented"
        say "$commented"
    fi
    unlink_module
    if [ -f "$CONF" ] && [ "$(conf_tool remove "$CONF")" = removed ]; then
        say "moonraker.conf: kestimator's [analysis]/[update_manager kestimator] lines removed"
    fi
    if [ -f "$CONF" ] && ! conf_tool has-block "$CONF"; then
        rm -f "$CONF".[0-9]*-[0-9]*.kestimator.bak  # install.sh's backups, of no use now
    fi
    for p in rpi linux osx; do
        link="$TOOLS/klipper_estimator_$p"
        if [ -L "$link" ] && [ "$(readlink "$link")" = "$LAUNCHER" ]; then
            rm -f "$link"
            if [ -e "$link.orig" ] || [ -L "$link.orig" ]; then
                mv "$link.orig" "$link"
                say "klipper_estimator_$p: the original klipper_estimator is back"
            else
                say "klipper_estimator_$p: kestimator's link removed (Moonraker downloads klipper_estimator when it starts)"
            fi
        fi
    done
    if state_has release_info; then
        rm -f "$TOOLS/release_info.json"
        if [ -e "$TOOLS/release_info.json.orig" ]; then
            mv "$TOOLS/release_info.json.orig" "$TOOLS/release_info.json"
        fi
    fi
    if state_has default_config; then
        rm -f "$TOOLS/default_estimator_cfg.json"
    fi
    if state_has profile && [ -f "$PROFILE" ] && [ -f "$VENV/profile-written" ] \
        && cmp -s "$PROFILE" "$VENV/profile-written"; then
        rm -f "$PROFILE"
        say "$PROFILE removed (it was install.sh's, unchanged)"
    fi
    hook="$(git -C "$REPO" rev-parse --git-path hooks/post-merge 2>/dev/null || true)"
    [ -z "$hook" ] || [ "${hook#/}" != "$hook" ] || hook="$REPO/$hook"
    if [ -n "$hook" ] && [ -f "$hook" ] && grep -qxF "$HOOK_MARK" "$hook"; then
        rm -f "$hook"
    fi
    local created
    created=$(sed -n 's/^created_folder=//p' "$STATE" 2>/dev/null || true)
    rm -f "$STATE"
    rm -rf "$VENV"
    # The folders install.sh made, deepest first, when nothing else is in them.
    if [ -n "$created" ]; then
        sort -r <<<"$created" | while IFS= read -r p; do rmdir "$p" 2>/dev/null || true; done
    fi
    say "kestimator uninstalled (its checkout $REPO stays; delete it if you like)."
    restart_moonraker "kestimator is uninstalled, but Moonraker still runs it until it restarts."
}

if [ "$UNINSTALL" = 1 ]; then
    uninstall
    exit 0
fi
if ! conf_tool has-block "$CONF" && ! conf_writable; then
    die "cannot write $CONF (or its folder): make it writable, then run ./install.sh again. Nothing was changed."
fi

# --- the build -------------------------------------------------------------
BUILD="${KESTIMATOR_BUILD:-}"
missing=()
python3 -c 'import ensurepip' 2>/dev/null || missing+=(python3-venv)
if [ "$BUILD" != pure ]; then
    command -v gcc >/dev/null || missing+=(gcc)
    python3 -c 'import os, sysconfig, sys
sys.exit(not os.path.exists(os.path.join(sysconfig.get_paths()["include"], "Python.h")))' \
        || missing+=(python3-dev)
fi
if [ "${#missing[@]}" -gt 0 ]; then
    if [ "$YES" = 1 ]; then
        say "Installing ${missing[*]} (sudo apt-get install)..."
        if ! { as_root apt-get update -qq && as_root apt-get install -y -qq "${missing[@]}"; }; then
            python3 -c 'import ensurepip' 2>/dev/null \
                || die "could not install python3-venv: sudo apt-get install python3-venv"
            say "apt-get failed: installing the pure-Python build (slower) instead of compiling it."
            BUILD=pure
        fi
    else
        die "missing apt packages: ${missing[*]}
Install them (sudo apt-get install ${missing[*]}) or run ./install.sh -y, which does.
(KESTIMATOR_BUILD=pure ./install.sh installs the slower pure-Python build without gcc.)"
    fi
fi

# The venv's build (plugins/moonraker/build-venv, also run by git after an update from
# Moonraker's panel: the post-merge hook below).
KESTIMATOR_BUILD="$BUILD" KESTIMATOR_KLIPPER_DIR="$KLIPPER_DIR" "$BUILDER" || die "building kestimator into $VENV failed (see above)"
version_line=$("$VENV/bin/kestimator" --version)
# After Moonraker's update manager pulls (git pull), git runs this hook before Moonraker
# restarts its services: the new commit is built as this one was.
hook="$(git -C "$REPO" rev-parse --git-path hooks 2>/dev/null || true)"
if [ -n "$hook" ]; then
    [ "${hook#/}" != "$hook" ] || hook="$REPO/$hook"
    hook="$hook/post-merge"
    if [ -e "$hook" ] && ! grep -qxF "$HOOK_MARK" "$hook"; then
        say "WARNING: $hook is not kestimator's: updates from Moonraker will not rebuild kestimator (run ./install.sh after one)."
    else
        mkdir -p "$(dirname "$hook")"
        # The builder's path quoted for sh: a quote, '$' or '`' in the checkout's path
        # stays a character of the name.
        printf '#!/bin/sh\n%s\nexec %s --as-installed\n' "$HOOK_MARK" "$(sh_quote "$BUILDER")" > "$hook"
        chmod +x "$hook"
    fi
fi
if [ "$BUILD" != pure ] && [[ "$version_line" == *pure* ]]; then
    say "The pure-Python build (slower) is installed: see the build line above (and $VENV/pip.log)."
fi

# --- the link Moonraker runs ---------------------------------------------------
sections=$(conf_tool sections "$CONF")
has_section() { grep -qx "$1" <<<"$sections"; }
option() { sed -n "s/^analysis\\.$1=//p" <<<"$sections"; }
PLATFORM=$(option platform)
[ -n "$PLATFORM" ] && [ "$PLATFORM" != auto ] || PLATFORM=$(platform)
SET_PLATFORM=""
if [ -z "$PLATFORM" ]; then
    PLATFORM=linux
    SET_PLATFORM="platform: linux"
fi
# mkdir -p, remembering each folder it made for --uninstall (the state file must exist).
make_folder() {
    local folder=$1 made=()
    while [ ! -d "$folder" ]; do
        made+=("$folder")
        folder=$(dirname "$folder")
    done
    mkdir -p "$1"
    touch "$STATE"
    for folder in "${made[@]}"; do
        state_add "created_folder=$folder"
    done
}
make_folder "$TOOLS"
LINK="$TOOLS/klipper_estimator_$PLATFORM"
if [ -L "$LINK" ] && [ "$(readlink "$LINK")" = "$LAUNCHER" ]; then
    :
else
    if [ -e "$LINK" ] || [ -L "$LINK" ]; then
        if [ -e "$LINK.orig" ] || [ -L "$LINK.orig" ]; then
            die "$LINK and $LINK.orig both exist: move one away"
        fi
        mv "$LINK" "$LINK.orig"
        say "klipper_estimator_$PLATFORM: the klipper_estimator there is kept as $(basename "$LINK").orig"
        if [ -e "$TOOLS/release_info.json" ] && [ ! -e "$TOOLS/release_info.json.orig" ]; then
            mv "$TOOLS/release_info.json" "$TOOLS/release_info.json.orig"
        fi
    fi
    ln -s "$LAUNCHER" "$LINK"
    state_add release_info
    rm -f "$TOOLS/release_info.json"  # Moonraker writes it again with kestimator's version
    say "Moonraker's klipper_estimator ($LINK) now runs kestimator."
fi

# --- kestimator's profile: the printer's own settings -----------------------
if [ -e "$PROFILE" ]; then
    say "kestimator profile $PROFILE kept as it is."
elif [ -f "$PRINTER_CFG" ]; then
    make_folder "$(dirname "$PROFILE")"
    # A TOML basic string: a '"' or '\' in the path escaped, control characters as \uXXXX.
    quoted=$(python3 -c 'import sys
print("\"%s\"" % "".join("\\" + c if c in "\"\\" else "\\u%04x" % ord(c)
                         if ord(c) < 32 or ord(c) == 127 else c for c in sys.argv[1]))' \
        "$PRINTER_CFG")
    printf '%s\n%s\n' "# Written by kestimator's install.sh: kestimator and Moonraker's [analysis] take this printer's limits from its printer.cfg." \
        "printer_cfg = $quoted" > "$PROFILE"
    cp "$PROFILE" "$VENV/profile-written"
    state_add profile
    say "kestimator profile $PROFILE: printer_cfg = $PRINTER_CFG"
else
    say "no $PRINTER_CFG: kestimator takes the limits from the config Moonraker dumps when Klipper is ready."
fi

# Moonraker analyses uploads only once its estimator config exists; it dumps it
# when Klipper is ready. With the printer.cfg named, write it now.
if ! has_section analysis || [ -z "$(option estimator_config)" ]; then
    if [ ! -e "$TOOLS/default_estimator_cfg.json" ] && [ -f "$PRINTER_CFG" ] && [ -f "$PROFILE" ]; then
        if "$LINK" dump-config > "$TOOLS/default_estimator_cfg.json.tmp" 2>/dev/null; then
            mv "$TOOLS/default_estimator_cfg.json.tmp" "$TOOLS/default_estimator_cfg.json"
            state_add default_config
        else
            rm -f "$TOOLS/default_estimator_cfg.json.tmp"
        fi
    fi
fi

# --- moonraker.conf -------------------------------------------------------------
block=""
if has_section analysis; then
    [ "$(option enable_estimator_updates | tr '[:upper:]' '[:lower:]')" = true ] \
        && say "WARNING: [analysis] enable_estimator_updates: True in moonraker.conf would replace kestimator with klipper_estimator: set it to False."
    [ "$(option enable_auto_analysis | tr '[:upper:]' '[:lower:]')" = true ] \
        || say "NOTE: moonraker.conf's own [analysis] is kept; set enable_auto_analysis: True in it to process every upload."
else
    block+="[analysis]
enable_auto_analysis: True
# must stay False: klipper_estimator's updater would replace kestimator
enable_estimator_updates: False
${SET_PLATFORM:+$SET_PLATFORM
}
"
fi
if ! has_section update_manager; then
    block+="[update_manager]

"
fi
if ! has_section "update_manager kestimator"; then
    origin=$(git -C "$REPO" remote get-url origin 2>/dev/null || true)
    branch=$(git -C "$REPO" symbolic-ref --short -q HEAD 2>/dev/null || echo main)
    if [ -n "$origin" ]; then
        # Moonraker restarts these after an update (it refuses updates during a print):
        # itself for the estimator, Klipper when the Klipper module is linked (the
        # module and its worker run the checkout's code).
        services=moonraker
        [ -d "$EXTRAS" ] && services="klipper moonraker"
        block+="[update_manager kestimator]
type: git_repo
path: $REPO
origin: $origin
primary_branch: $branch
managed_services: $services
install_script: install.sh
"
    else
        say "WARNING: this checkout has no 'origin' remote: no [update_manager kestimator] (Moonraker could not update it)."
    fi
fi
if [ -n "$block" ]; then
    backup="$CONF.$(date +%Y%m%d-%H%M%S).kestimator.bak"
    cp -p "$CONF" "$backup"
    conf_tool add "$CONF" "${block%$'\n'}"$'\n' >/dev/null
    say "moonraker.conf: added $(grep -o '^\[[^]]*\]' <<<"$block" | tr '\n' ' ')(backup: $backup)"
else
    say "moonraker.conf: nothing to add."
fi

# --- the Klipper module ---------------------------------------------------------
link_module
if [ "$FRONTEND_SETTINGS" = 1 ]; then
    state_add frontend_settings
    # Its address kept for --uninstall (the last one given replaces an earlier one).
    if ! state_has "moonraker_url=$MOONRAKER_URL"; then
        sed -i '/^moonraker_url=/d' "$STATE"
        printf 'moonraker_url=%s\n' "$MOONRAKER_URL" >> "$STATE"
    fi
    frontend_settings
fi

say "Installed: $version_line"
restart_moonraker "kestimator ($version_line) is installed: Moonraker's klipper_estimator runs it and moonraker.conf has its lines, but Moonraker runs them only once restarted."
say "Check: GET /server/analysis/status says \"estimator_ready\": true and kestimator's version."
