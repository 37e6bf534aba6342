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
MODULE="$REPO/plugins/klipper/kestimator.py"
BUILDER="$REPO/plugins/moonraker/build-venv"
HOOK_MARK="# kestimator: build the new commit (install.sh wrote this hook)"
YES=0
UNINSTALL=0
ALLOW_ROOT=0
RESTART=1
FRONTEND_SETTINGS=0
MOONRAKER_URL="http://127.0.0.1:7125"
SETTINGS_TOOL="$REPO/plugins/klipper/frontend_settings.py"
STATE_NAME="kestimator-install.state"

usage() {
    cat <<EOF
Usage: ./install.sh [-d DIR] [-k DIR] [-y] [--no-restart] [--allow-root]
                    [--frontend-settings [--moonraker URL]]
       ./install.sh --uninstall [-d DIR] [-k DIR] [-y] [--no-restart] [--allow-root]

Installs kestimator in its own virtualenv ($VENV), compiled
when gcc and Python's headers are there, and makes Moonraker's [analysis] run it
in place of klipper_estimator; adds [analysis] and [update_manager kestimator]
to moonraker.conf (once, after a dated backup) and writes kestimator's profile
naming the printer.cfg. Where Klipper is, it links kestimator's Klipper module
into klippy/extras/ (a [kestimator] section in printer.cfg turns it on).
Run it again after any change: it changes nothing twice.

  -d DIR         Moonraker's data folder (default: ~/printer_data)
  -k DIR         Klipper's checkout (default: ~/klipper)
  -y             answer yes: install missing apt packages (sudo apt-get), restart Moonraker
  --uninstall    undo: klipper_estimator back, moonraker.conf as it was before
  --no-restart   never restart Moonraker
  --allow-root   run as root (only if Moonraker itself runs as root)
  --frontend-settings
                 set Mainsail's progress, estimate and ETA settings (and Fluidd's
                 progress) so they show the Klipper module's time, through
                 Moonraker's database API; --uninstall puts back what was there
  --moonraker URL  Moonraker's address for that (default: http://127.0.0.1:7125)
  -h, --help     this text

KESTIMATOR_BUILD=pure installs the pure-Python build without trying to compile.
EOF
}

say() { printf '%s\n' "$*"; }
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
        --moonraker) [ $# -ge 2 ] || die "--moonraker needs a URL"; MOONRAKER_URL="$2"; shift ;;
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

[ -d "$DATA" ] || die "no Moonraker data folder at $DATA (give it with -d DIR)"
DATA=$(cd "$DATA" && pwd -P)
CONF="$DATA/config/moonraker.conf"
[ -f "$CONF" ] || die "no $CONF: is $DATA Moonraker's data folder? (-d DIR)"
TOOLS="$DATA/tools/klipper_estimator"
STATE="$TOOLS/$STATE_NAME"
PRINTER_CFG="$DATA/config/printer.cfg"
PROFILE="${XDG_CONFIG_HOME:-$HOME/.config}/kestimator/config.toml"
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

# Edits moonraker.conf, keeping every byte it did not add (python3: configparser,
# as Moonraker reads it). Prints what it did, one line each.
conf_tool() {
    python3 - "$@" <<'PYTHON'
import configparser, sys
action, conf = sys.argv[1], sys.argv[2]
BEGIN = "# >>> kestimator (install.sh; ./install.sh --uninstall removes this block)"
END = "# <<< kestimator"
text = open(conf, encoding="utf-8").read()
if action == "sections":
    parser = configparser.ConfigParser(strict=False, interpolation=None)
    parser.read_string(text)
    for name in parser.sections():
        print(name)
    if parser.has_section("analysis"):
        for key in ("platform", "estimator_config", "enable_auto_analysis",
                    "enable_estimator_updates"):
            if parser.has_option("analysis", key):
                print("analysis.%s=%s" % (key, parser.get("analysis", key).strip()))
elif action == "add":
    block = sys.argv[3]
    if BEGIN in text:
        sys.exit(0)
    with open(conf, "a", encoding="utf-8") as f:
        f.write("\n" + BEGIN + "\n" + block + END + "\n")
    print("added")
elif action == "remove":
    start = text.find("\n" + BEGIN + "\n")
    if start < 0:
        sys.exit(0)
    end = text.find("\n" + END + "\n", start)
    if end < 0:
        sys.exit("moonraker.conf: %r without %r: remove kestimator's lines by hand"
                 % (BEGIN, END))
    text = text[:start] + text[end + len(END) + 2:]
    with open(conf + ".kestimator-tmp", "w", encoding="utf-8") as f:
        f.write(text)
    import os, shutil
    shutil.copymode(conf, conf + ".kestimator-tmp")
    os.replace(conf + ".kestimator-tmp", conf)
    print("removed")
PYTHON
}

restart_moonraker() {
    if [ "$RESTART" = 0 ]; then
        say "Moonraker not restarted (--no-restart): sudo systemctl restart moonraker"
        return
    fi
    local answer=n
    if [ "$YES" = 1 ]; then
        answer=y
    elif [ -t 0 ]; then
        read -r -p "Restart Moonraker now (sudo systemctl restart moonraker)? [y/N] " answer
    fi
    case "$answer" in
        y|Y|yes) as_root systemctl restart moonraker && say "Moonraker restarted." ;;
        *) say "Moonraker not restarted: run sudo systemctl restart moonraker" ;;
    esac
}

state_has() { [ -f "$STATE" ] && grep -qx "$1" "$STATE"; }
state_add() { state_has "$1" || printf '%s\n' "$1" >> "$STATE"; }

# The Klipper module: klippy/extras/kestimator.py, a link to this checkout's file (as
# Klipper add-ons install), kept out of Klipper's git status so its updates stay clean.
EXTRAS="$KLIPPER_DIR/klippy/extras"
MODULE_LINK="$EXTRAS/kestimator.py"
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
    else
        ln -s "$MODULE" "$MODULE_LINK"
        say "Klipper module linked: $MODULE_LINK"
    fi
    local exclude="$KLIPPER_DIR/.git/info/exclude"
    if [ -d "$KLIPPER_DIR/.git/info" ] && ! grep -qx "klippy/extras/kestimator.py" "$exclude" 2>/dev/null; then
        printf '%s\n' "klippy/extras/kestimator.py" >> "$exclude"
    fi
    say "To turn it on, add a [kestimator] section to printer.cfg and restart Klipper (see plugins/klipper/README.md)."
}
unlink_module() {
    if [ -L "$MODULE_LINK" ] && [ "$(readlink "$MODULE_LINK")" = "$MODULE" ]; then
        rm -f "$MODULE_LINK"
        say "Klipper module link removed: remove [kestimator] from printer.cfg before Klipper restarts."
    fi
}

# Mainsail's and Fluidd's settings, through Moonraker's database API (never their files).
frontend_settings() {
    if python3 "$SETTINGS_TOOL" --moonraker "$MOONRAKER_URL" "$@"; then
        return 0
    fi
    say "WARNING: Mainsail's and Fluidd's settings were not changed (Moonraker at $MOONRAKER_URL: see above); run again with --frontend-settings when Moonraker runs."
}

uninstall() {
    local p link
    if state_has frontend_settings; then
        frontend_settings --undo
    fi
    unlink_module
    if [ -f "$CONF" ] && [ "$(conf_tool remove "$CONF")" = removed ]; then
        say "moonraker.conf: kestimator's [analysis]/[update_manager kestimator] lines removed"
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
    rm -f "$STATE"
    rm -rf "$VENV"
    say "kestimator uninstalled (its checkout $REPO stays; delete it if you like)."
    restart_moonraker
}

if [ "$UNINSTALL" = 1 ]; then
    uninstall
    exit 0
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
KESTIMATOR_BUILD="$BUILD" "$BUILDER" || die "building kestimator into $VENV failed (see above)"
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
        printf '#!/bin/sh\n%s\nexec "%s" --as-installed\n' "$HOOK_MARK" "$BUILDER" > "$hook"
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
mkdir -p "$TOOLS"
touch "$STATE"
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
    mkdir -p "$(dirname "$PROFILE")"
    printf '%s\n%s\n' "# Written by kestimator's install.sh: kestimator and Moonraker's [analysis] take this printer's limits from its printer.cfg." \
        "printer_cfg = \"$PRINTER_CFG\"" > "$PROFILE"
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
    frontend_settings
fi

say "Installed: $version_line"
restart_moonraker
say "Check: GET /server/analysis/status says \"estimator_ready\": true and kestimator's version."
