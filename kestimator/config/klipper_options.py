"""Which options Klipper accepts in the config sections kestimator reads.

Generated from mainline Klipper 84104bbbd's own config reads: every `config.get*('name'`
call of klippy/toolhead.py, klippy/kinematics/*.py, klippy/extras/gcode_arcs.py,
klippy/extras/firmware_retraction.py, klippy/extras/input_shaper.py,
klippy/extras/safe_z_home.py and klippy/extras/homing_override.py. An [extruder]
section is shared by the extruder, its stepper, its heater and its temperature sensor of
any type: it accepts every option name that any part of klippy reads (and the numbered
options of the sensor tables), so that no valid config is refused and a misspelt option
is still caught.
"""

from __future__ import annotations

# [printer]: toolhead.py, then the options of each kinematics module.
PRINTER_OPTIONS = frozenset((
    "kinematics", "max_accel", "max_velocity", "minimum_cruise_ratio", "square_corner_velocity"
))
KINEMATICS_OPTIONS: dict[str, frozenset[str]] = {
    "cartesian": frozenset(("max_z_accel", "max_z_velocity")),
    "corexy": frozenset(("max_z_accel", "max_z_velocity")),
    "corexz": frozenset(("max_z_accel", "max_z_velocity")),
    "delta": frozenset((
        "delta_radius", "max_z_accel", "max_z_velocity", "minimum_z_position", "print_radius"
    )),
    "deltesian": frozenset((
        "max_z_accel", "max_z_velocity", "min_angle", "minimum_z_position", "print_width",
        "slow_ratio"
    )),
    "generic_cartesian": frozenset((
        "axis", "endstop_pin", "max_z_accel", "max_z_velocity", "primary_carriage",
        "safe_distance"
    )),
    "hybrid_corexy": frozenset(("max_z_accel", "max_z_velocity")),
    "hybrid_corexz": frozenset(("max_z_accel", "max_z_velocity")),
    "none": frozenset(),
    "polar": frozenset(("max_angular_velocity", "max_z_accel", "max_z_velocity")),
    "rotary_delta": frozenset((
        "max_z_velocity", "minimum_z_position", "shoulder_height", "shoulder_radius")),
    "winch": frozenset(),
    # Kalico v2026.07.00's own (klippy/kinematics/limited_*.py, over cartesian / corexy /
    # corexz's).
    "limited_cartesian": frozenset((
        "max_x_accel", "max_x_velocity", "max_y_accel", "max_y_velocity", "max_z_accel",
        "max_z_velocity", "scale_xy_accel")),
    "limited_corexy": frozenset((
        "max_x_accel", "max_y_accel", "max_z_accel", "max_z_velocity", "scale_xy_accel")),
    "limited_corexz": frozenset((
        "max_x_accel", "max_x_velocity", "max_y_accel", "max_y_velocity", "max_z_accel",
        "max_z_velocity", "scale_xy_accel")),
}
SECTION_OPTIONS: dict[str, frozenset[str]] = {
    "safe_z_home": frozenset((
        "home_xy_position", "z_hop", "z_hop_speed", "speed", "move_to_previous")),
    "homing_override": frozenset((
        "set_position_x", "set_position_y", "set_position_z", "axes", "gcode")),
    "gcode_arcs": frozenset(("resolution",)),
    "firmware_retraction": frozenset((
        "retract_length", "retract_speed", "unretract_extra_length", "unretract_speed")),
    "input_shaper": frozenset((
        "shaper_type", "shaper_type_x", "shaper_type_y", "shaper_type_z", "shaper_freq_x",
        "shaper_freq_y", "shaper_freq_z", "damping_ratio_x", "damping_ratio_y",
        "damping_ratio_z"
    )),
}
# Every option name any part of klippy reads with a literal name.
ANY_KLIPPY_OPTION = frozenset((
    "accel", "accel_chip", "accel_chip_x", "accel_chip_y", "accel_chip_z", "accel_per_hz",
    "accel_per_hz_z", "adaptive_margin", "adc1", "adc2", "adc_channel", "adc_voltage",
    "address_pin", "aht10_report_time", "algorithm", "algorithm", "analog_pullup_resistor",
    "analog_range", "analog_range_", "anchor_", "angle", "apiserver", "arm_length",
    "arm_x_length", "auto_cancel_variation", "auto_load_speed", "axes", "axes_map", "axis",
    "axis", "baud", "beta", "bicubic_tension", "bme280_gas_heat_duration",
    "bme280_gas_target_temp", "bme280_iir_filter", "bme280_oversample_hum",
    "bme280_oversample_pressure", "bme280_oversample_temp", "build_versions", "bus", "cal_dia1",
    "cal_dia2", "calibrate", "calibrate", "calibrate_end_x", "calibrate_end_y",
    "calibrate_start_x", "calibrate_start_y", "calibrate_x", "calibrate_y",
    "calibration_bed_temp", "calibration_extruder_temp", "calibration_position",
    "calibration_temp", "canbus_interface", "canbus_uuid", "carriage", "carriages", "carriages",
    "chain_count", "chain_length", "chain_position", "check_gain_time", "chip", "chips",
    "class", "clear", "clear_homed", "clk_pin", "clock", "clock_freq", "clock_pin",
    "color_order", "combination_method", "command", "commands", "compensation_end_x",
    "compensation_end_y", "compensation_start_x", "compensation_start_y", "config", "context",
    "contrast", "control", "control_pin", "coolstep_threshold", "counts_per_gram", "cs_pin",
    "current", "cycle_time", "damping_ratio_", "data", "data_pin", "data_ready_pin",
    "deactivate_on_each_sample", "debounce_delay", "debuginput", "debugoutput",
    "default_nominal_filament_diameter", "default_prefix", "default_type", "delta_radius",
    "descend_z", "description", "detection_length", "diag0_pin", "diag1_pin", "diag_pin",
    "dictionary", "dictionary_", "dir_pin", "direction", "display_group", "dout_pin",
    "drift_calibration_min_temp", "drv_status", "ds18_report_time", "en_pin", "enable",
    "enable_flow_compensation", "enable_force_move", "enable_global_chop", "enable_pin",
    "encoder_fast_rate", "encoder_pins", "encoder_steps_per_detent", "endstop_accuracy",
    "endstop_align_zero", "endstop_pin", "enumerations", "errors", "event", "event_delay",
    "extruder", "extruder_heating_z", "fade_end", "fade_start", "fade_target", "fan_speed",
    "feedrate_normal", "feedrate_splice", "field", "filament_diameter", "file", "filename",
    "filename", "frequency", "full_steps_per_rotation", "gain", "gcode_axis", "gcode_fd",
    "gcode_id", "gear_ratio", "global_chop_delay", "group", "hardware_pwm", "hd44780_data",
    "hd44780_protocol_init", "hd44780_slot", "heater", "heater", "heater_pin", "heater_temp",
    "heaters", "heating_gain", "high_velocity_threshold", "hold_current", "home_attempt_num",
    "home_xy_position", "homing_positive_dir", "homing_retract_dist", "homing_retract_speed",
    "homing_speed", "horizontal_move_z", "host_mcu", "htu21d_hold_master", "htu21d_report_time",
    "htu21d_resolution", "hysteresis", "hz_per_sec", "i2c_address", "i2c_bus", "i2c_mcu",
    "i2c_software_scl_pin", "i2c_speed", "icon16x16", "icon5x8", "id", "idle_current_percent",
    "idle_speed", "idle_timeout", "index", "initial_angle", "initial_blue", "initial_duration",
    "initial_green", "initial_pulse_width", "initial_red", "initial_white", "inline_resistor",
    "input", "input_max", "input_min", "input_mux", "input_step", "insert_gcode",
    "instantaneous_corner_velocity", "intb_pin", "interpolate", "invert", "is_runout", "json",
    "kick_start_time", "kinematics", "lcd_type", "lift_speed", "line_length",
    "lm75_report_time", "load", "logging", "lower_arm_length", "max_accel", "max_adjust",
    "max_angular_velocity", "max_delta", "max_diameter", "max_difference", "max_error",
    "max_extrude_cross_section", "max_extrude_only_accel", "max_extrude_only_distance",
    "max_extrude_only_velocity", "max_freq", "max_freq_z", "max_power", "max_sensor_hz",
    "max_smoothing", "max_speed", "max_temp", "max_validation_temp", "max_velocity",
    "max_z_accel", "max_z_adjustment", "max_z_velocity", "maximum_deviation",
    "maximum_mcu_duration", "maximum_pulse_width", "maximum_servo_angle", "mcu", "mcu",
    "measurement_delay", "measurement_interval", "menu_reverse_navigation", "menu_root",
    "menu_timeout", "mesh_max", "mesh_min", "mesh_origin", "mesh_radius", "method", "method",
    "microsteps", "min_angle", "min_diameter", "min_extrude_temp", "min_freq", "min_speed",
    "min_temp", "minimum_cruise_ratio", "minimum_pulse_width", "minimum_z_position", "mode",
    "motion_queue", "move_check_distance", "move_speed", "move_to_previous", "msg", "name",
    "name", "nozzle_diameter", "ns", "objects", "off_below", "oid", "oracle_out", "output",
    "output", "overflows", "parameter", "params", "path", "pause_delay", "pause_on_runout",
    "pga", "pga_bypass", "pid_deriv_time", "pid_kd", "pid_ki", "pid_kp", "pin", "pin_move_time",
    "pin_up_reports_not_triggered", "pin_up_touch_mode_reports_triggered", "pins", "point",
    "points", "populate", "position", "position_endstop", "position_max", "position_min",
    "prefix", "pressure_advance", "pressure_advance_smooth_time", "primary_carriage",
    "print_radius", "print_width", "printer", "probe_accel", "probe_height", "probe_speed",
    "probe_with_touch_mode", "profile", "pullup_resistor", "pwm", "pwm_clock", "pwm_cycle_time",
    "queue_name", "radius", "rate", "raw_dia1", "raw_dia2", "realtime", "recover_velocity",
    "recovery_time", "reference_tare_counts", "reg", "reg_drive_current", "register", "remove",
    "rename_existing", "render_only", "reset", "reset_pin", "resistance1", "resistance2",
    "resistance3", "resolution", "responses", "restart_method", "resting_z", "retract_length",
    "retract_speed", "retries", "retry_tolerance", "revision", "rotation_distance",
    "round_probe_count", "rref", "rst_pin", "rtd_nominal_r", "rtd_num_of_wires",
    "rtd_reference_r", "rtd_use_50hz_filter", "run_current", "runout_gcode", "rx_pin",
    "safe_distance", "sample_period", "sample_rate", "sample_retract_dist", "samples",
    "samples_result", "samples_result", "samples_tolerance", "samples_tolerance_retries",
    "save", "scale", "scan_overshoot", "sclk_pin", "screw_thread", "second_homing_speed",
    "select_pins", "sense_resistor", "sensor", "sensor_adc1", "sensor_adc2", "sensor_list",
    "sensor_mcu", "sensor_orientation", "sensor_path", "sensor_pin", "sensor_specific",
    "sensor_temperature1", "sensor_temperature2", "sensor_type", "sercom", "serial",
    "serial_no", "set_homed", "set_output_mode", "set_position_", "settings", "sg4_result",
    "sg_result", "sg_result", "shaper_freq_", "shaper_type", "shaper_type", "shaper_type_",
    "shaper_type_", "shoulder_height", "shoulder_radius", "sht3x_report_time", "shutdown_clock",
    "shutdown_speed", "shutdown_value", "slow_ratio", "smooth_time", "software_version",
    "speed", "spi_bus", "spi_software_sclk_pin", "spi_speed", "spi_status", "split_delta_z",
    "square_corner_velocity", "standstill_power_down", "start_reason", "stealthchop_threshold",
    "step_gen_time", "step_pin", "step_pulse_duration", "stepper", "stepper",
    "stepper_both_edge", "stepper_optimized_unstep", "stepper_step_both_edge", "steppers",
    "stop_on_endstop", "stow_on_each_sample", "sweeping_accel", "sweeping_accel_z",
    "sweeping_period", "switch_pin", "tachometer_pin", "tachometer_poll_interval",
    "tachometer_ppr", "tap", "tap_threshold", "tap_z_offset", "target_temp",
    "tc_averaging_count", "tc_type", "tc_use_50hz_filter", "temp_coeff", "temperature1",
    "temperature2", "temperature3", "template", "text", "timeout", "toolhead", "trigger_phase",
    "tx_pin", "type", "type", "uart_address", "uart_pin", "unretract_extra_length",
    "unretract_speed", "upper_arm_length", "use_current_dia_while_delay", "val", "value",
    "value", "variable", "vcomh", "velocity", "version", "voltage_offset", "vref", "wiper",
    "x_adjust", "x_offset", "xy_skew", "xz_skew", "y_adjust", "y_offset", "yz_skew", "z",
    "z_adjust", "z_adjust_off_above", "z_hop", "z_hop_speed", "z_offset",
    "zero_reference_position"
))
# Names klippy builds at run time for modules an [extruder] may use: extras/bus.py (software
# SPI and I2C pins of a temperature sensor), extras/adc_temperature.py (numbered tables).
BUILT_OPTION_NAMES = frozenset((
    "spi_software_miso_pin", "spi_software_mosi_pin", "spi_software_sclk_pin",
    "i2c_software_scl_pin", "i2c_software_sda_pin"))
