"""Which G-code commands real Klipper registers, and for which config section.

    python3 tools/klipper_commands.py probe CONFIG.cfg [--add-sections] > registered.json
    python3 tools/klipper_commands.py table > kestimator/klipper_commands.py

`probe` starts unmodified Klipper (the oracle's tree, 84104bbbd: ORACLE_KLIPPER and
ORACLE_PYTHON, ../shared/tools/oracle/README.md) in batch mode on a printer config and
prints, once Klipper is ready, every command its gcode object then holds
(`GCodeDispatch.ready_gcode_handlers`), each with the config section whose module
registered it, the modules each module loaded (`Printer.load_object`) and the config's
kinematics. Nothing is linked into Klipper's tree: this file is run by Klipper's own Python
(`ProbeServer`), which imports klippy and loads its C helper once, then forks a fresh
process for each probe; there, before `klippy.main()`, it wraps `Printer.load_object` and
`GCodeDispatch.register_command` to note who calls them.

Batch mode needs the MCU's data dictionary, and Klipper's shipped configs name the pins,
SPI and I2C buses of many MCUs: the probe gives Klipper the Linux-process MCU's dictionary
(`out/klipper.dict`) with its pin and bus names widened to every name those configs use
(batch mode never talks to an MCU; the names are only looked up).

`table` probes every config Klipper ships (`config/printer-*.cfg`, `generic-*.cfg`,
`kit-*.cfg`, `example-*.cfg`) and Klipper's own test configs (`test/klippy/*.cfg`), each with
the sections every Mainsail/Fluidd setup adds (`ADDED_SECTIONS`), and writes the table
kestimator reads: for each module, the commands it registers and the modules it loads.
`tests/test_klipper_commands.py` holds that table to what Klipper registers.
"""
from __future__ import annotations

import glob
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
import traceback
from typing import IO, Any, NoReturn

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

# What every Mainsail/Fluidd printer.cfg adds (and a macro and a delayed_gcode); %(dir)s is
# a scratch directory.
ADDED_SECTIONS = """
[gcode_macro KESTIMATOR_PROBE_MACRO]
gcode:
  G4 P1

[delayed_gcode KESTIMATOR_PROBE_DELAYED]
gcode:
  G4 P1

[virtual_sdcard]
path: %(dir)s

[pause_resume]

[display_status]

[exclude_object]

[respond]

[save_variables]
filename: %(dir)s/variables.cfg
"""
# Probes beyond the shipped configs, each on PROBE_BASE with its sections added: modules
# that register commands but that no config Klipper ships has (angle.py without a stepper,
# as its calibration needs NumPy; load_cell, palette2 and ldc1612 alone are left out: NumPy,
# a serial device, a probe's part), and the project's own Klipper module, [kestimator]
# (plugins/klipper/; its worker is not started: batch mode ends before it would be used).
PROJECT_MODULE = os.path.join(ROOT, "plugins", "klipper", "kestimator")
PROBE_BASE = "config/printer-creality-ender3-v2-2020.cfg"
EXTRA_PROBES = {
    "kestimator": "\n[kestimator]\npython: /bin/false\n",
    "extras-1": """

[z_thermal_adjust]
temp_coeff: 0.01
sensor_type: EPCOS 100K B57560G104F
sensor_pin: PC12
min_temp: 0
max_temp: 70

[hall_filament_width_sensor]
adc1: PC10
adc2: PC11
default_nominal_filament_diameter: 1.75
measurement_delay: 70

[angle my_angle]
sensor_type: tle5012b
cs_pin: PD12

[skew_correction]
""",
    "extras-2": """
[tsl1401cl_filament_width_sensor]
pin: PC10
default_nominal_filament_diameter: 1.75
measurement_delay: 70
max_difference: 0.2

[temperature_probe my_probe]
sensor_type: EPCOS 100K B57560G104F
sensor_pin: PC11

[probe]
pin: PC12
z_offset: 1
""",
}

# Files among those that are no printer config Klipper can start with: example-extras.cfg
# is a catalogue of sections (no [mcu] serial), the delta calibration test configs are
# completed by their tests, load_cell.cfg needs NumPy (not in the oracle's venv).
NOT_PRINTER_CONFIGS = frozenset(("example-extras.cfg", "delta_calibrate.cfg",
                                 "rotary_delta_calibrate.cfg", "load_cell.cfg"))


def oracle_paths() -> tuple[str, str] | None:
    """(Klipper tree, its Python) when the oracle's Klipper is set up here, else None."""
    klipper = os.environ.get("ORACLE_KLIPPER", os.path.expanduser("~/oracle/klipper"))
    python = os.environ.get("ORACLE_PYTHON", os.path.expanduser("~/oracle/venv/bin/python"))
    if (os.path.exists(os.path.join(klipper, "klippy", "klippy.py"))
            and os.path.exists(os.path.join(klipper, "out", "klipper.dict"))
            and os.path.exists(python)):
        return klipper, python
    return None


def widened_dictionary(linux_dict: str, out: str) -> None:
    """The Linux MCU's dictionary with the pin and bus names of every MCU Klipper's configs
    use (AVR/STM32/SAM ports PA0.., LPC P0.0.., RP2040 gpio0.., analog inputs)."""
    with open(linux_dict) as f:
        doc = json.load(f)
    enums = doc["enumerations"]
    pins: dict[str, Any] = {}
    base = 0
    for name, count in ([("P%s0" % port, 32) for port in "ABCDEFGHIJKLZ"]
                        + [("P%d.0" % port, 32) for port in range(5)]
                        + [("gpio0", 300), ("analog0", 32), ("ar0", 100), ("PIN_0", 64)]):
        pins[name] = [base, count]
        base += count
    for port in range(4):
        pins["gpio%d_0" % port] = [base, 32]
        base += 32
    for name in ("ADC_TEMPERATURE", "ADC_VREF"):
        pins[name] = base
        base += 1
    enums["pin"] = pins
    # Bus names one by one (a name ending in a digit with a count would be a range); the
    # bus of value 0 is the MCU's default.
    buses = ["spi%d%s" % (n, s) for n in range(8) for s in ("", "a", "b", "c")]
    buses += ["usart%d" % n for n in range(8)] + ["ssp0", "ssp1", "spi"]
    buses += ["spidev%d.%d" % (a, b) for a in range(8) for b in range(4)]
    buses += ["spi0_gpio4_gpio3_gpio2", "spi1_gpio12_gpio11_gpio10", "spi1_PA6_PA7_PA5",
              "spi1_PB4_PB5_PB3", "spi2_PB14_PB15_PB13"]
    enums["spi_bus"] = {name: n for n, name in enumerate(buses)}
    i2c = ["i2c%d%s" % (n, s) for n in range(8) for s in ("", "a", "b", "c")]
    i2c += ["twi", "i2c.0", "i2c.1", "i2c1_PB6_PB7", "i2c1_PB8_PB9"]
    enums["i2c_bus"] = {name: n for n, name in enumerate(i2c)}
    with open(out, "w") as f:
        json.dump(doc, f)


def mcu_names(cfg_text: str) -> list[str]:
    """The names of the config's secondary MCUs ([mcu NAME])."""
    return re.findall(r"^\[mcu\s+([^\]\s]+)\s*\]", cfg_text, re.MULTILINE)


class ProbeServer:
    """Klipper's Python (the oracle's) running `_serve`: klippy imported and its C helper
    loaded once, then each probe in a process forked from it, fresh as a new Klipper
    process but for the interpreter's start, klippy's imports and cffi's parse of the C
    helper's declarations (about 0.15 s of CPU a probe). Its bytecode is kept in a folder
    of its own (PYTHONPYCACHEPREFIX, whatever PYTHONDONTWRITEBYTECODE says): Klipper's
    modules are compiled once, not once a probe (about 0.13 s more)."""

    def __init__(self) -> None:
        paths = oracle_paths()
        if paths is None:
            raise RuntimeError("the oracle's Klipper is not set up (.ci/klipper-setup "
                               "builds it)")
        self.klipper = paths[0]
        self._tmp = tempfile.TemporaryDirectory(prefix="kcommands-server-")
        env = dict(os.environ, PYTHONPYCACHEPREFIX=os.path.join(self._tmp.name, "pycache"))
        env.pop("PYTHONDONTWRITEBYTECODE", None)
        self._log = os.path.join(self._tmp.name, "server.log")
        with open(self._log, "wb") as log:
            self._proc = subprocess.Popen(
                [paths[1], os.path.abspath(__file__), "--serve",
                 os.path.join(self.klipper, "klippy")], stdin=subprocess.PIPE,
                stdout=subprocess.PIPE, stderr=log, cwd=self.klipper, env=env, text=True)

    def run(self, out: str, argv: list[str], output: str, timeout: float) -> int:
        """klippy.main() with `argv` in a forked process, writing the probe to `out` and
        its own output to `output`: its exit code. TimeoutExpired when it ran `timeout`
        seconds (it is killed)."""
        stdin, stdout = self._pipes()
        stdin.write(json.dumps({"out": out, "argv": argv, "output": output,
                                "timeout": timeout}) + "\n")
        stdin.flush()
        line = stdout.readline()
        if not line:
            with open(self._log, errors="replace") as f:
                tail = f.read()[-2000:]
            raise RuntimeError("Klipper's probe server stopped (rc %s):\n%s"
                               % (self._proc.poll(), tail))
        answer = json.loads(line)
        if answer["timed_out"]:
            raise subprocess.TimeoutExpired(argv, timeout)
        return int(answer["rc"])

    def _pipes(self) -> tuple[IO[str], IO[str]]:
        assert self._proc.stdin is not None and self._proc.stdout is not None
        return self._proc.stdin, self._proc.stdout

    def close(self) -> None:
        stdin, stdout = self._pipes()
        try:
            stdin.close()
            self._proc.wait(30)
        except (OSError, subprocess.TimeoutExpired):
            self._proc.kill()
            self._proc.wait()
        stdout.close()
        self._tmp.cleanup()

    def __enter__(self) -> ProbeServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def probe(cfg: str, add_sections: bool, timeout: float = 120.0, extra: str = "",
          server: ProbeServer | None = None) -> dict[str, Any]:
    """Run Klipper in batch mode on `cfg` (plus ADDED_SECTIONS, and `extra`): what it
    registered. `server`: the ProbeServer to run it in (one of its own without)."""
    if server is None:
        with ProbeServer() as own:
            return probe(cfg, add_sections, timeout, extra, own)
    klipper = server.klipper
    with tempfile.TemporaryDirectory(prefix="kcommands-") as tmp:
        with open(cfg, errors="replace") as f:
            text = f.read()
        if add_sections:
            text += "\n" + ADDED_SECTIONS % {"dir": tmp}
        text += extra
        conf = os.path.join(tmp, "printer.cfg")
        with open(conf, "w") as f:
            f.write(text)
        dictionary = os.path.join(tmp, "mcu.dict")
        widened_dictionary(os.path.join(klipper, "out", "klipper.dict"), dictionary)
        batch = os.path.join(tmp, "batch.gcode")
        with open(batch, "w") as f:
            f.write("")
        out = os.path.join(tmp, "out.json")
        log = os.path.join(tmp, "klippy.log")
        args = [conf, "-i", batch, "-o", os.devnull, "-d", dictionary, "-l", log]
        for name in mcu_names(text):
            args += ["-d", "%s=%s" % (name, dictionary)]
        output = os.path.join(tmp, "output")
        returncode = server.run(out, args, output, timeout)
        if not os.path.exists(out):
            tail = ""
            if os.path.exists(log):
                with open(log, errors="replace") as f:
                    tail = f.read()[-2000:]
            with open(output, errors="replace") as f:
                printed = f.read()[-2000:]
            raise RuntimeError("Klipper did not get ready on %s (rc %d):\n%s%s"
                               % (cfg, returncode, tail, printed))
        with open(out) as f:
            result: dict[str, Any] = json.load(f)
    return result


def _serve(klippy_dir: str) -> None:
    """Klipper's Python as ProbeServer runs it: klippy and its C helper loaded, then for
    each request (a JSON line on stdin) a forked process runs the probe (`_probe_child`);
    its exit code, or that it ran out of time and was killed, is the answer line."""
    sys.path.insert(0, klippy_dir)
    import chelper  # type: ignore[import-not-found]
    import gcode  # type: ignore[import-not-found]  # noqa: F401
    import klippy  # type: ignore[import-not-found]  # noqa: F401
    import toolhead  # type: ignore[import-not-found]  # noqa: F401

    chelper.get_ffi()
    for line in sys.stdin:
        request = json.loads(line)
        sys.stdout.flush()
        pid = os.fork()
        if pid == 0:
            _probe_child(request, klippy_dir)
        deadline = time.monotonic() + float(request["timeout"])
        timed_out = False
        while True:
            done, status = os.waitpid(pid, os.WNOHANG)
            if done:
                break
            if time.monotonic() >= deadline:
                os.kill(pid, signal.SIGKILL)
                _, status = os.waitpid(pid, 0)
                timed_out = True
                break
            time.sleep(0.005)
        sys.stdout.write(json.dumps({"rc": os.waitstatus_to_exitcode(status),
                                     "timed_out": timed_out}) + "\n")
        sys.stdout.flush()


def _probe_child(request: dict[str, Any], klippy_dir: str) -> NoReturn:
    """The forked process of one probe: its output to the request's file, then klippy."""
    code = 1
    try:
        fd = os.open(request["output"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        null = os.open(os.devnull, os.O_RDONLY)
        os.dup2(null, 0)
        os.dup2(fd, 1)
        os.dup2(fd, 2)
        try:
            _in_klipper(request["out"], klippy_dir, list(request["argv"]))
            code = 0
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else int(exc.code is not None)
        except BaseException:
            traceback.print_exc()
    finally:
        try:
            sys.stdout.flush()
            sys.stderr.flush()
        finally:
            os._exit(code)


def _in_klipper(out: str, klippy_dir: str, argv: list[str]) -> None:
    """Inside Klipper's Python: note who registers each command, run klippy.main()."""
    sys.path.insert(0, klippy_dir)
    import gcode as kgcode  # type: ignore[import-not-found]
    import klippy  # type: ignore[import-not-found]
    import toolhead as ktoolhead  # type: ignore[import-not-found]

    loading: list[str] = []
    owners: dict[str, set[str]] = {}
    loads: dict[str, set[str]] = {}
    in_toolhead: list[bool] = []

    def module_of(section: str) -> str:
        return section.split()[0]

    def frame_owner() -> str:
        # Outside any load_object: the outermost Klipper module file on the stack (the
        # extruder, a kinematics, an event handler's module), but idex_modes.py's
        # dual carriages wherever they are.
        found = ""
        for frame in traceback.extract_stack():
            parts = frame.filename.replace("\\", "/").split("/")
            if len(parts) >= 2 and parts[-2] in ("extras", "kinematics"):
                name = parts[-1][:-3] if parts[-1].endswith(".py") else parts[-1]
                if name == "__init__":
                    name = parts[-2]
                name = ("kinematics/" if parts[-2] == "kinematics" else "") + name
                if name == "kinematics/idex_modes":
                    return name
                found = found or name
        return found or ("<toolhead>" if in_toolhead else "<core>")

    orig_load = klippy.Printer.load_object

    def load_project_module(self: Any, config: Any, section: str) -> Any:
        # The project's own Klipper module ([kestimator], plugins/klipper/), loaded as
        # klippy's load_object loads an extras package a user linked.
        import importlib.util
        if section in self.objects:
            return self.objects[section]
        spec = importlib.util.spec_from_file_location(
            "extras.kestimator", os.path.join(PROJECT_MODULE, "__init__.py"),
            submodule_search_locations=[PROJECT_MODULE])
        assert spec is not None and spec.loader is not None
        mod = importlib.util.module_from_spec(spec)
        sys.modules["extras.kestimator"] = mod
        spec.loader.exec_module(mod)
        self.objects[section] = mod.load_config(config.getsection(section))
        return self.objects[section]

    def load_object(self: Any, config: Any, section: str, *args: Any) -> Any:
        # Who loads it: the module being loaded, else the Klipper file that asks (a
        # kinematics, the extruder), else the config's sections or toolhead.py's defaults.
        parent = module_of(loading[-1]) if loading else frame_owner()
        if parent == "<core>":
            parent = "<config>"
        loading.append(section)
        try:
            if section == "kestimator":
                obj = load_project_module(self, config, section)
            else:
                obj = orig_load(self, config, section, *args)
        finally:
            loading.pop()
        if obj is not None and module_of(section) != parent:
            loads.setdefault(parent, set()).add(module_of(section))
        return obj
    klippy.Printer.load_object = load_object

    orig_register = kgcode.GCodeDispatch.register_command

    def registrant() -> str:
        return module_of(loading[-1]) if loading else frame_owner()

    def register_command(self: Any, cmd: str, func: Any, *args: Any, **kw: Any) -> Any:
        if func is not None:
            owners.setdefault(cmd, set()).add(registrant())
        return orig_register(self, cmd, func, *args, **kw)
    kgcode.GCodeDispatch.register_command = register_command

    orig_mux = kgcode.GCodeDispatch.register_mux_command

    def register_mux_command(self: Any, cmd: str, *args: Any, **kw: Any) -> Any:
        owners.setdefault(cmd, set()).add(registrant())
        return orig_mux(self, cmd, *args, **kw)
    kgcode.GCodeDispatch.register_mux_command = register_mux_command

    orig_add = ktoolhead.add_printer_objects

    def add_printer_objects(config: Any) -> Any:
        in_toolhead.append(True)
        try:
            return orig_add(config)
        finally:
            in_toolhead.pop()
    ktoolhead.add_printer_objects = add_printer_objects

    orig_ready = kgcode.GCodeDispatch._handle_ready

    def handle_ready(self: Any) -> Any:
        printer = self.printer
        kin = printer.lookup_object("toolhead").get_kinematics()
        sections = []
        configfile = printer.lookup_object("configfile")
        status = configfile.get_status(None)
        sections = sorted(status.get("config", {}))
        macros = {}
        for section, options in status.get("config", {}).items():
            if section.split()[0] == "gcode_macro" and len(section.split()) > 1:
                macros[section.split()[1].upper()] = (
                    options.get("rename_existing", "").upper() or None)
        doc = {
            "macros": macros,
            "commands": {cmd: sorted(owners.get(cmd, ())) or ["?"]
                         for cmd in sorted(self.ready_gcode_handlers)},
            "loads": {k: sorted(v) for k, v in sorted(loads.items())},
            "sections": sections,
            "kinematics": type(kin).__module__.split(".")[-1],
        }
        with open(out, "w") as f:
            json.dump(doc, f, indent=1, sort_keys=True)
        return orig_ready(self)
    kgcode.GCodeDispatch._handle_ready = handle_ready
    sys.argv = [os.path.join(klippy_dir, "klippy.py")] + argv
    klippy.main()


def shipped_configs(klipper: str) -> list[str]:
    """Every printer config Klipper ships, and its own test configs."""
    found = []
    for pattern in ("config/printer-*.cfg", "config/generic-*.cfg", "config/kit-*.cfg",
                    "config/example-*.cfg", "test/klippy/*.cfg"):
        found += sorted(path for path in glob.glob(os.path.join(klipper, pattern))
                        if os.path.basename(path) not in NOT_PRINTER_CONFIGS)
    return found


def config_path(klipper: str, name: str) -> tuple[str, str]:
    """The file of a config `probe_all` names ("config/x.cfg", "klippy/x.cfg", or
    "PROBE:config/x.cfg" for EXTRA_PROBES), and the text added to it beyond
    ADDED_SECTIONS."""
    extra = ""
    if ":" in name:
        probe, name = name.split(":", 1)
        extra = EXTRA_PROBES[probe]
    return os.path.join(klipper, "test" if name.startswith("klippy/") else "", name), extra


def probe_all(configs: list[str]) -> tuple[dict[str, dict[str, Any]], dict[str, str]]:
    """Each config's probe (with ADDED_SECTIONS; PROBE_BASE also with each of
    EXTRA_PROBES, named "PROBE:" + its name), and why the others did not get ready.

    The probes run in one ProbeServer: about 0.2 s of CPU each, where a new Klipper
    process for each took 0.43 s on this project's machines (PYTHONDONTWRITEBYTECODE set:
    Klipper's sources compiled afresh in each)."""
    done: dict[str, dict[str, Any]] = {}
    failed: dict[str, str] = {}
    runs = [(os.path.relpath(cfg, os.path.dirname(os.path.dirname(cfg))), cfg, "")
            for cfg in configs]
    for name, cfg, _ in list(runs):
        if name == PROBE_BASE:
            runs += [(probe + ":" + name, cfg, text) for probe, text in EXTRA_PROBES.items()]
    with ProbeServer() as server:
        for name, cfg, extra in runs:
            try:
                done[name] = probe(cfg, True, extra=extra, server=server)
            except (RuntimeError, subprocess.TimeoutExpired) as exc:
                failed[name] = str(exc).strip().splitlines()[-1][:200]
    return done, failed


# Who registered a command (the probe's names) -> the module of the table: the extruder's
# commands are [extruder]'s; idex_modes.py's are [dual_carriage]'s; generic_cartesian's
# stepper helper is that kinematics'; klippy's own files are always there.
_OWNER_MODULE = {"kinematics/extruder": "extruder", "kinematics/idex_modes": "dual_carriage",
                 "kinematics/kinematic_stepper": "kinematics/generic_cartesian"}
CORE = ("<core>", "<toolhead>")


def table_module(owner: str) -> str:
    """The table's module for a registrant the probe names."""
    return _OWNER_MODULE.get(owner, owner)


def macro_commands(result: dict[str, Any]) -> set[str]:
    """The commands a probed config's [gcode_macro]s define (and the names they rename)."""
    names = set(result.get("macros", {}))
    names |= {renamed for renamed in result.get("macros", {}).values() if renamed}
    return names


def build_table(done: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Klipper's registrations over every probed config, as the table kestimator reads."""
    core: set[str] = set()
    defaults: set[str] = set()
    commands: dict[str, set[str]] = {}
    loads: dict[str, set[str]] = {}
    for result in done.values():
        macros = macro_commands(result)
        for cmd, owners in result["commands"].items():
            if cmd in macros:
                continue
            for owner in owners:
                if owner in CORE:
                    core.add(cmd)
                else:
                    commands.setdefault(table_module(owner), set()).add(cmd)
        for parent, children in result["loads"].items():
            if parent == "<config>":
                continue
            if parent == "<toolhead>":
                defaults.update(children)
            else:
                module = table_module(parent)
                loads.setdefault(module, set()).update(c for c in children if c != module)
    return {"core": sorted(core), "defaults": sorted(defaults),
            "commands": {m: sorted(c) for m, c in sorted(commands.items())},
            "loads": {m: sorted(c) for m, c in sorted(loads.items()) if c}}


def _wrapped(names: list[str], indent: int) -> str:
    """Quoted names, wrapped to the project's line length."""
    lines, line = [], ""
    for name in names:
        item = '"%s", ' % name
        if line and indent + len(line) + len(item) > 95:
            lines.append(line.rstrip())
            line = ""
        line += item
    lines.append(line.rstrip())
    return ("\n" + " " * indent).join(lines)


def table_source(table: dict[str, Any], configs: list[str]) -> str:
    """kestimator/klipper_commands.py: the table, as Python."""
    out = ['"""The G-code commands Klipper 84104bbbd registers, by the module that registers '
           'them.',
           "",
           "Owns the data: `python3 tools/klipper_commands.py table` wrote it from what real "
           "Klipper",
           "(84104bbbd, batch mode) held once ready on the %d printer configs it ships and its "
           "own" % len(configs),
           "test configs, each with the sections every Mainsail/Fluidd setup adds, and on "
           "modules no",
           "shipped config has (the tool's EXTRA_PROBES). Do not edit it:",
           "run the tool again; `tests/test_klipper_commands.py` holds it to Klipper. What "
           "the names",
           "mean to a config's sections is `kestimator.klipper_modules`'.",
           '"""',
           "",
           "from __future__ import annotations",
           "",
           "from typing import Final",
           "",
           "KLIPPER_COMMIT: Final = \"84104bbbd\"",
           "# Registered whatever the config: klippy/gcode.py, configfile.py, toolhead.py.",
           "CORE_COMMANDS: Final = frozenset((",
           "    " + _wrapped(table["core"], 4),
           "))",
           "# The modules toolhead.py loads whatever the config.",
           "DEFAULT_MODULES: Final = (",
           "    " + _wrapped(table["defaults"], 4),
           ")",
           "# Module -> the commands it registers (itself or through what it imports; a mux",
           "# command for any of its values). \"kinematics/NAME\" is a kinematics' own;",
           "# \"extruder\" every [extruderN]'s; \"dual_carriage\" kinematics/idex_modes.py's.",
           "MODULE_COMMANDS: Final[dict[str, tuple[str, ...]]] = {"]
    for module, names in table["commands"].items():
        head = '    "%s": (' % module
        out.append(head + _wrapped(names, len(head)) + "),")
    out += ["}", "# Module -> the modules it loads (`Printer.load_object`).",
            "MODULE_LOADS: Final[dict[str, tuple[str, ...]]] = {"]
    for module, names in table["loads"].items():
        head = '    "%s": (' % module
        out.append(head + _wrapped(names, len(head)) + "),")
    out.append("}")
    return "\n".join(out) + "\n"


def main(argv: list[str]) -> int:
    if argv[:1] == ["--serve"]:
        _serve(argv[1])
        return 0
    if argv[:1] == ["probe"]:
        print(json.dumps(probe(argv[1], "--add-sections" in argv), indent=1, sort_keys=True))
        return 0
    if argv[:1] == ["table"]:
        paths = oracle_paths()
        if paths is None:
            print("the oracle's Klipper is not set up (.ci/klipper-setup)", file=sys.stderr)
            return 1
        configs = shipped_configs(paths[0])
        done, failed = probe_all(configs)
        if failed:
            for name, why in sorted(failed.items()):
                print("%s: %s" % (name, why), file=sys.stderr)
            return 1
        sys.stdout.write(table_source(build_table(done), configs))
        return 0
    if argv[:1] == ["survey"]:
        paths = oracle_paths()
        assert paths is not None
        done, failed = probe_all(shipped_configs(paths[0]))
        json.dump({"done": done, "failed": failed}, sys.stdout, indent=1, sort_keys=True)
        return 0
    print(__doc__)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
