"""The virtual ODrive's board: identity, power, settings, readings and the diagnostic
functions of the firmware's table (a mixin of
:class:`leglib.device.virtual.firmware.VirtualODrive`).

The board presented is the thesis's: an ODrive v3.6, **56 V** variant (Table 4.1),
powered from the thesis's 6S LiPo pack (Table 4.4). Everything here follows fw-v0.5.6
(file:line; 0.5.1 where marked); what the model cannot know (the MCU's stack high-water
marks, task timings, the level of a floating pin) raises :class:`UnmodeledError` at the
read, naming it and why, rather than reading a made-up number.
"""

from __future__ import annotations

import math
import struct

from ...errors import DeviceLostError
from ...twin import layout as L
from .tree import UnmodeledError, c_value

# -- the board presented --------------------------------------------------------------
HW_VERSION = (3, 6, 56)          # odrive_main.h:210-212: major, minor, variant = HW_VERSION_VOLTAGE
# the thesis's supply: a 6S LiPo (Table 4.4: 22.2 V nominal, 25.2 V full, 5300 mAh, 30 C).
# The pack is taken at 24.0 V open-circuit (about half charged: assumed) with 30 mOhm of
# internal and lead resistance (6 cells of about 3 mOhm plus the leads: assumed), so the bus
# sags by about 0.1 V per 3 A drawn.
BATTERY_VOLTAGE = 24.0           # [V]
BATTERY_RESISTANCE = 0.030       # [ohm]
VBUS_NOISE = 0.05                # [V] rms of the bus measurement (ADC)
FET_AMBIENT = 25.0               # [degC] the FET thermistors: the bench's ambient (no thermal model)
ADC_REF = 3.3                    # [V] low_level.cpp:27 adc_ref_voltage
ADC_FULL_SCALE = 4096            # low_level.cpp:26: a 12-bit conversion
ADC_HIGH = 4095 / ADC_FULL_SCALE * ADC_REF   # a pin at the rail: the largest count (low_level.cpp:304-306)

# error codes of the bus and the brake resistor
ODRIVE_ERROR_INVALID_BRAKE_RESISTANCE = 0x80     # odrive-interface.yaml ODrive.Error (0.5.6)
MOTOR_ERROR_SYSTEM_LEVEL = L.MOTOR_ERROR_SYSTEM_LEVEL
AXIS051_BRAKE_RESISTOR_DISARMED = 0x10           # fw-v0.5.1 odrive-interface.yaml ODrive.Axis.Error
AXIS051_MOTOR_DISARMED = 0x20
AXIS051_MOTOR_FAILED = 0x40                      # declared, never set by fw 0.5.1
_BUS_FAULTS_051 = L.MOTOR_ERROR_DC_BUS_OVER_REGEN_CURRENT | L.MOTOR_ERROR_DC_BUS_OVER_CURRENT

# v3.5/v3.6 GPIOs (board.cpp:203-220): (ADC channel or None, pin name); GPIO0 is a dummy
GPIO_PINS = ((None, None), (0, "PA0"), (1, "PA1"), (2, "PA2"), (3, "PA3"), (14, "PC4"), (None, "PB2"),
             (None, "PA15"), (None, "PB3"), (None, "PB4"), (None, "PB5"), (None, "PC9"), (None, "PB6"),
             (None, "PB7"), (None, "PC15"), (None, "PB8"), (None, "PB9"))
# GpioMode values (odrive-interface.yaml ODrive.GpioMode, fw-v0.5.6)
(GPIO_DIGITAL, GPIO_PULL_UP, GPIO_PULL_DOWN, GPIO_ANALOG, GPIO_UART_A, GPIO_UART_B, GPIO_UART_C, GPIO_CAN_A,
 GPIO_I2C_A, GPIO_SPI_A, GPIO_PWM, GPIO_ENC0, GPIO_ENC1, GPIO_ENC2, GPIO_MECH_BRAKE, GPIO_STATUS) = range(16)
# the alternate functions each pin has (board.cpp:229-255): other modes leave the pin
# unconfigured and set ``misconfigured`` (main.cpp:710-715)
ALTERNATE = {1: {GPIO_UART_A, GPIO_PWM}, 2: {GPIO_UART_A, GPIO_PWM}, 3: {GPIO_UART_B, GPIO_PWM},
             4: {GPIO_UART_B, GPIO_PWM}, 9: {GPIO_ENC0}, 10: {GPIO_ENC0}, 12: {GPIO_I2C_A, GPIO_ENC1},
             13: {GPIO_I2C_A, GPIO_ENC1}, 15: {GPIO_CAN_A, GPIO_I2C_A}, 16: {GPIO_CAN_A, GPIO_I2C_A}}
_PLAIN_MODES = {GPIO_DIGITAL, GPIO_PULL_UP, GPIO_PULL_DOWN, GPIO_MECH_BRAKE, GPIO_STATUS, GPIO_ANALOG}

# FreeRTOS threads: stack size [B] and priority as osThreadGetPriority reports it (CMSIS-RTOS
# osPriority: Low -2, Normal 0, High 2; axis 0 runs at High + 1, board.cpp:128). Sources:
# axis.hpp:189, interface_usb.cpp:18,235, interface_uart.cpp:25,192, freertos.c:80 and
# main.cpp:839, odrive_can.hpp:43 and odrive_can.cpp:39, low_level.cpp:28,409
THREADS_056 = {"axis": (2048, 3), "usb": (4096, 0), "uart": (4096, 0), "startup": (2048, 0),
               "can": (1024, 0), "analog": (1024, -2)}

# NVIC configuration of fw-v0.5.6 (priority as NVIC_GetPriority returns it with 4 preemption
# bits, NVIC_PRIORITYGROUP_4: stm32f4xx_hal_msp.c:67) and the rate of the periodic ones
# [per s]: irqn -> (priority, source, rate or None for event-driven)
INTERRUPTS_056 = {
    -12: (0, "stm32f4xx_hal_msp.c:71", 0.0), -11: (0, "stm32f4xx_hal_msp.c:73", 0.0),
    -10: (0, "stm32f4xx_hal_msp.c:75", 0.0), -5: (3, "stm32f4xx_hal_msp.c:77", None),
    -4: (0, "stm32f4xx_hal_msp.c:79", 0.0), -2: (15, "stm32f4xx_hal_msp.c:81", None),
    -1: (15, "main.c:211 (FreeRTOS tick, 1 kHz)", 1000.0),
    6: (1, "board.cpp:309", 0.0), 7: (1, "board.cpp:311", 0.0), 8: (1, "board.cpp:313", 0.0),
    9: (1, "board.cpp:315", 0.0), 10: (1, "board.cpp:317", 0.0), 23: (1, "board.cpp:319", 0.0),
    40: (1, "board.cpp:321", 0.0),
    11: (4, "dma.c:75 (SPI3 RX: DRV8301)", None), 13: (10, "dma.c:79 (UART4 RX)", None),
    15: (10, "dma.c:82 (UART4 TX)", None), 16: (10, "dma.c:85 (USART2 RX)", None),
    17: (10, "dma.c:88 (USART2 TX)", None), 47: (3, "dma.c:91 (SPI3 TX: DRV8301)", None),
    19: (9, "can.c:123", None), 20: (9, "can.c:125", None), 21: (9, "can.c:127", None), 22: (9, "can.c:129", None),
    44: (0, "board.cpp:327 (TIM8 update: twice per control period)", 16000.0),
    45: (0, "stm32f4xx_hal_timebase_TIM.c:86 (HAL tick, 1 kHz)", 1000.0),
    50: (1, "tim.c:471 (PWM input capture)", 0.0), 52: (10, "usart.c:154 (UART4)", None),
    38: (10, "usart.c:206 (USART2)", None), 67: (6, "usbd_conf.c:117 (USB)", None),
    77: (5, "board.cpp:324 (control loop, 8 kHz)", 8000.0),
}
# DMA streams of fw-v0.5.6: stream -> (channel, priority, peripheral, configured when)
DMA_056 = {0: (0, 1, "SPI3_RX", "always"), 7: (0, 2, "SPI3_TX", "always"),
           2: (4, 0, "UART4_RX", "config.enable_uart_a"), 4: (4, 0, "UART4_TX", "config.enable_uart_a"),
           5: (4, 0, "USART2_RX", "config.enable_uart_b"), 6: (4, 0, "USART2_TX", "config.enable_uart_b"),
           8: (0, 0, "ADC1", "always")}


class BoardMixin:
    """The board's identity, power supply, settings store, readings and diagnostics."""

    # -- settings (catalog rows' Setting store) ----------------------------------------
    def _factory_settings(self, rows) -> dict:
        """{None|0|1: {generic path: default}} of the Setting rows ``rows`` (the firmware's
        defaults of the board presented; 0 / False where the firmware's struct leaves a
        member value-initialized)."""
        from .tree import Setting  # load time: with the wire's import below, at the first board
        from .wire import firmware_defaults  # load time: the tables live with the wire (which imports this module)
        defaults = firmware_defaults(self.firmware)
        out = {None: {}, 0: {}, 1: {}}
        for row in rows:
            if not isinstance(row.store, Setting) or not row.active(self.firmware):
                continue
            hit = defaults.get(row.path)
            for a, _ in row.concrete():
                if hit is None:
                    value = False if row.kind is bool else 0.0 if row.kind is float else 0
                else:
                    value = hit["axes"][a] if ("axes" in hit and a is not None) else hit["value"]
                out[a][row.path] = c_value(row.store.codec, row.kind(value))
        return out

    def _setting_default(self, a, key):
        return self._factory_values[a][key]

    def _saved_size(self) -> int:
        """Bytes of the saved configuration: the wire sizes of its endpoints (the firmware's
        own count is the size of its config structs, main.cpp:169-174)."""
        from .wire import _FORMATS, endpoint_table, flatten  # load time: the tables live with the wire
        return sum(struct.calcsize("<" + _FORMATS[e["type"]])
                   for path, e in flatten(endpoint_table(self.firmware)).items()
                   if e["type"] in _FORMATS and ".config." in f".{path}.")

    def _setting(self, a, key):
        return self._settings[a][key]

    # -- power: the battery and the bus -------------------------------------------------
    def _vbus(self) -> float:
        """The bus voltage now [V]: the pack's voltage less its resistance times the bus
        current of the last tick (the kernel's own value, C_VBUS - C_VBUS_R * ibus)."""
        C, S = self.st.C[0, 0], self.st.AS[0, 0]
        return float(C[L.C_VBUS] - C[L.C_VBUS_R] * S[L.S_IBUS])

    def _vbus_voltage(self) -> float:
        return self._vbus() + VBUS_NOISE * float(self._rng.standard_normal())

    def _set_brake_resistance(self, value: float):
        self._board["brake_resistance"] = value
        self._sync_brake()
        self._check_brake_resistance()

    def _sync_brake(self):
        """The kernel's brake resistor from the board's state: it takes current while armed
        and its resistance is positive. A resistance that is not positive never brakes
        (fw-v0.5.1 low_level.cpp:631-652: the duty clamps to 0; 0.5.2+ trips on it); the
        kernel keeps a positive placeholder for its reciprocal."""
        r = float(self._board["brake_resistance"])
        ok = r > 0.0
        self.st.C[0, 0, L.C_BRAKE_R] = r if ok else 1.0
        self.st.C[0, 0, L.C_BRAKE_ON] = 1.0 if (self._brake_armed and ok) else 0.0

    def _check_brake_resistance(self):
        """low_level.cpp:332-336 (every PWM update, armed or not): an enabled brake resistor
        with a resistance that is not positive disarms the board (0.5.2+)."""
        if self.firmware != "0.5.1" and self._board["enable_brake_resistor"] \
                and not float(self._board["brake_resistance"]) > 0.0:
            self._disarm_with_error(ODRIVE_ERROR_INVALID_BRAKE_RESISTANCE)

    def _disarm_with_error(self, error: int):
        """main.cpp:313-321: both motors disarmed with a system-level error, the brake
        resistor disarmed, the board's error set."""
        st = self.st
        for a in range(2):
            st.AI[0, a, L.I_MOTOR_ERR] |= MOTOR_ERROR_SYSTEM_LEVEL
            st.AI[0, a, L.I_AXIS_ERR] |= L.AXIS_ERROR_MOTOR_FAILED       # motor.cpp:340
            self._disarm(a)
        self._brake_armed = False
        self._sync_brake()
        st.AI[0, 0, L.I_SYS_ERR] |= error

    def _board_events(self):
        """What the board does between control ticks that the kernel leaves to the host:
        the brake resistor's state follows the kernel's (a bus fault disarms it), the
        brake's saturation latch, and on fw 0.5.1 the axes' own view of a fault."""
        st = self.st
        vbus = self._vbus()
        self._vbus_trip_check(vbus)
        if self._brake_armed and st.C[0, 0, L.C_BRAKE_ON] == 0.0 and float(self._board["brake_resistance"]) > 0.0:
            self._brake_armed = False          # the kernel's bus checks disarmed it
        if vbus > 0 and float(st.AS[0, 0, L.S_BRAKE_I]) * float(st.C[0, 0, L.C_BRAKE_R]) / vbus >= 0.95:
            self._brake_saturated = True                     # low_level.cpp:350-353
        if self.firmware == "0.5.1":
            self._board_events_051()

    def _vbus_trip_check(self, vbus: float):
        """main.cpp:300-305 as the kernel's _board_checks does it, at the host's step: a
        trip level written between two runs trips here at once (the kernel checks every
        tick of a run: a board that checks its bus never takes the vectorized path, which
        has no board checks; leglib/twin/vector.py)."""
        st = self.st
        if not st.C[0, 0, L.C_VBUS_CHECKS] > 0.0:
            return
        under = not (vbus >= float(st.C[0, 0, L.C_UV_TRIP]))
        over = not (vbus <= float(st.C[0, 0, L.C_OV_TRIP]))
        if not (under or over):
            return
        if self.firmware == "0.5.1":            # fw-v0.5.1 axis.cpp:173-176
            for a in range(2):
                st.AI[0, a, L.I_AXIS_ERR] |= ((L.AXIS_ERROR_DC_BUS_UNDER_VOLTAGE if under else 0)
                                              | (L.AXIS_ERROR_DC_BUS_OVER_VOLTAGE if over else 0))
                self._disarm(a)
        else:
            self._disarm_with_error((L.ODRIVE_ERROR_DC_BUS_UNDER_VOLTAGE if under else 0)
                                    | (L.ODRIVE_ERROR_DC_BUS_OVER_VOLTAGE if over else 0))

    def _vbus_trips_reachable(self) -> bool:
        """Whether a bus current the motors can draw (both at the sense range, 60.75 A)
        could take the bus past a trip level (the step batch's vectorized path does not
        check it)."""
        st = self.st
        ocv, r = float(st.C[0, 0, L.C_VBUS]), float(st.C[0, 0, L.C_VBUS_R])
        swing = r * 2 * 61.0
        return not (ocv - swing >= float(st.C[0, 0, L.C_UV_TRIP]) and ocv + swing <= float(st.C[0, 0, L.C_OV_TRIP]))

    def _board_events_051(self):
        """fw-v0.5.1: a bus fault is low_level_fault (low_level.cpp:87-95): the motors get
        the error and the brake resistor is disarmed until the next boot (it is armed only in
        start_adc_pwm, low_level.cpp:239-243). The axis then sees BRAKE_RESISTOR_DISARMED in
        every check, IDLE included, and MOTOR_DISARMED if it was running (axis.cpp:168-172);
        0.5.1 never sets MOTOR_FAILED on the axis."""
        st = self.st
        if any(int(st.AI[0, a, L.I_MOTOR_ERR]) & _BUS_FAULTS_051 for a in range(2)) and self._brake_armed:
            self._brake_armed = False
            self._sync_brake()
        for a, ax in enumerate(self._axis):
            err = int(st.AI[0, a, L.I_AXIS_ERR])
            if err & AXIS051_MOTOR_FAILED:
                err &= ~AXIS051_MOTOR_FAILED
                if ax["state"] not in (1, 0):        # running something but IDLE: the motor was disarmed
                    err |= AXIS051_MOTOR_DISARMED
            if not self._brake_armed:
                err |= AXIS051_BRAKE_RESISTOR_DISARMED
            st.AI[0, a, L.I_AXIS_ERR] = err

    # -- counters and clocks -------------------------------------------------------------
    def _ticks(self) -> int:
        """Control-loop iterations since this boot (8 kHz), as the uint32 counters wrap."""
        return int(round((self.time - self._boot_t0) * self.twin.config.loop_frequency)) & 0xFFFFFFFF

    def _r_ticks(self, *args) -> int:
        # n_evt_control_loop / n_evt_sampling (main.cpp:342,366), the motors' measurement
        # and PWM events (motor.cpp:605), 0.5.1's axis loop_counter: one per control period
        return self._ticks()

    def _r_usb_count(self, generic: str) -> int:
        # interface_usb.cpp: one packet received and one sent per request-response
        return self._usb_packets & 0xFFFFFFFF

    def _r_task_timers_armed(self, generic: str = "") -> bool:
        # board.cpp:499,573: the next control iteration samples the task timers and clears
        # the flag; every read is at least one USB transaction (> 1 control period) later
        return False

    def _r_unmodelled(self, *args):
        generic, reason = args[-2], args[-1]
        where = generic if len(args) == 2 else generic.replace("axis*", f"axis{args[0]}")
        raise UnmodeledError(f"odrv.{where}: {reason}")

    def _r_setting(self, *args):
        """A read-only member of a config struct: the firmware's default (nothing changes it
        on this bench: the anticogging calibration that would is refused)."""
        a, key = (None, args[0]) if len(args) == 1 else args
        if key in self._settings[a]:
            return self._settings[a][key]
        from .wire import firmware_defaults  # load time: the tables live with the wire
        hit = firmware_defaults(self.firmware).get(key)
        return 0 if hit is None else (hit["axes"][a] if "axes" in hit and a is not None else hit["value"])

    def _r_board(self, what: str):
        return {"variant": HW_VERSION[2]}[what]

    def _r_user_config_loaded(self, generic: str = "") -> int:
        # main.cpp:671-673: the size of the configuration read from flash, 0 when none
        # (the size here: the wire sizes of the saved settings, not the firmware's structs)
        return int(self._config_bytes)

    def _r_misconfigured(self, generic: str = "") -> bool:
        # main.cpp:678-681,710-765: an enabled UART the board lacks (uart_c: board.cpp:37),
        # a GPIO in a mode it has no alternate function for, or a communication mode whose
        # interface is disabled
        s = self._settings[None]
        if self.firmware == "0.5.1":
            return False
        bad = bool(s.get("config.enable_uart_c", False))
        enables = {GPIO_UART_A: "config.enable_uart_a", GPIO_UART_B: "config.enable_uart_b",
                   GPIO_UART_C: "config.enable_uart_c", GPIO_CAN_A: "config.enable_can_a",
                   GPIO_I2C_A: "config.enable_i2c_a"}
        for g in range(1, 17):
            mode = s.get(f"config.gpio{g}_mode")
            if mode is None or mode in _PLAIN_MODES:
                continue
            if mode not in ALTERNATE.get(g, set()):
                bad = True
            elif mode in enables and not s.get(enables[mode], False):
                bad = True
        return bad

    def _r_system_stats(self, generic: str):
        name = generic.split(".", 1)[1]
        if name.startswith("stack_size_") and self.firmware != "0.5.1":
            return THREADS_056[name[len("stack_size_"):]][0]
        if name.startswith("prio_") and self.firmware != "0.5.1":
            return THREADS_056[name[len("prio_"):]][1]
        raise UnmodeledError(f"odrv.{generic}: the MCU's heap and stack high-water marks are not "
                             f"simulated (main.cpp:261-288)")

    def _r_brake_saturated(self, generic: str = "") -> bool:
        # low_level.cpp:350-353: latched once the brake duty reaches 95 %
        return bool(self._brake_saturated)

    # -- the thermistors -----------------------------------------------------------------
    def _r_temperature(self, a: int, generic: str) -> float:
        if ".fet_thermistor." in generic:
            return FET_AMBIENT
        # the motor thermistor's polynomial at the open input's level (no thermistor wired;
        # thermistor.cpp:22-37): the coefficients are zero by default (main.cpp:140), so 0
        prefix = "axis*.motor.motor_thermistor.config." if self.firmware != "0.5.1" else "axis*.motor_thermistor.config."
        coeffs = [self._settings[a][f"{prefix}poly_coefficient_{i}"] for i in range(4)]
        if any(coeffs[:3]):
            raise UnmodeledError(f"odrv.{generic.replace('axis*', f'axis{a}')}: the motor thermistor's input "
                                 f"is open (nothing is wired): its polynomial's reading is undefined")
        return float(coeffs[3])

    # -- diagnostics functions -----------------------------------------------------------
    def _test_function(self, delta: int) -> int:
        # odrive_main.h:184-187: a static counter, wrapping as an int32
        self._test_counter = (self._test_counter + int(delta) + 2**31) % 2**32 - 2**31
        return self._test_counter

    def _oscilloscope_val(self, index: int) -> float:
        # oscilloscope.hpp:15, odrive_main.h:227-231: no trigger or data source is set, so
        # the buffer never captures and holds zeros
        return 0.0 if int(index) < 4096 else math.nan

    def _get_drv_fault(self) -> int:
        return 0        # main.cpp:226-234: both DRV8301 report no fault

    def _gpio_mode(self, g: int) -> int:
        return int(self._settings[None].get(f"config.gpio{g}_mode", GPIO_DIGITAL))

    def _get_adc_voltage(self, gpio: int) -> float:
        """low_level.cpp:250-309: the ADC reading of the pin, count / 4096 * 3.3 V (a pin
        at the rail reads 4095 counts); -3.3 V for a pin without an ADC channel
        (get_adc_relative_voltage_ch returns -1)."""
        g = int(gpio)
        channel = GPIO_PINS[g][0] if 0 <= g < len(GPIO_PINS) else None
        if channel is None:
            return -ADC_REF
        mode = self._gpio_mode(g)
        if mode == GPIO_UART_A:
            return ADC_HIGH      # the UART line idles high (TX driven, RX pulled up: main.cpp:739-744)
        if mode == GPIO_PULL_UP:
            return ADC_HIGH
        if mode == GPIO_PULL_DOWN:
            return 0.0
        raise UnmodeledError(f"odrv.get_adc_voltage({g}): nothing is wired to GPIO{g} on this bench; "
                             f"a floating input reads an undefined voltage")

    def _get_gpio_states(self) -> int:
        """main.cpp:507-514: bit i is GPIO i's input level."""
        value = 0
        floating = []
        for g in range(1, 17):
            if GPIO_PINS[g][1] is None:
                continue
            level = self._gpio_level(g)
            if level is None:
                floating.append(g)
            elif level:
                value |= 1 << g
        if floating:
            raise UnmodeledError(f"odrv.get_gpio_states(): GPIO {', '.join(map(str, floating))} are "
                                 f"floating inputs with nothing wired on this bench: their level is undefined")
        return value

    def _gpio_level(self, g: int):
        """The input level of GPIO ``g`` on this bench, None where it floats."""
        mode = self._gpio_mode(g)
        if mode == GPIO_ANALOG:
            return False          # the input data register reads 0 in analog mode
        if mode in (GPIO_UART_A, GPIO_UART_B, GPIO_CAN_A, GPIO_PULL_UP, GPIO_I2C_A):
            return True           # idle lines and pull-ups (main.cpp:739-777)
        if mode == GPIO_PULL_DOWN:
            return g in self._index_pins_high()
        if mode in (GPIO_ENC0, GPIO_ENC1):
            a = 0 if mode == GPIO_ENC0 else 1
            phase = self._quadrature_state(a)
            return bool(phase[0] if g in (9, 12) else phase[1])
        return None

    def _quadrature_state(self, a: int) -> tuple[bool, bool]:
        """The A and B lines of axis ``a``'s encoder: the quadrature state of its count."""
        n = int(self.st.AI[0, a, L.I_COUNTS] - self.st.C[0, a, L.C_COUNT_OFFSET]) % 4
        return ((False, False), (True, False), (True, True), (False, True))[n]

    def _index_pins_high(self) -> set:
        return set()              # the Z pulse is a quarter count wide: sampled low

    def _get_interrupt_status(self, irqn: int) -> int:
        """main.cpp:470-484: priority | count << 8 | enabled << 31 (0xffffffff out of range)."""
        irqn = int(irqn)
        if irqn < -14 or irqn >= 240:
            return 0xFFFFFFFF
        if self.firmware == "0.5.1":
            raise UnmodeledError("odrv.get_interrupt_status: not modelled for fw 0.5.1")
        hit = INTERRUPTS_056.get(irqn)
        if hit is None:
            return 0 if irqn >= 0 else 0x80000000   # not configured: priority 0, never fired
        prio, source, rate = hit
        enabled = irqn < 0 or self._irq_enabled(irqn)
        if rate is None and enabled:
            raise UnmodeledError(f"odrv.get_interrupt_status({irqn}): the count of this event-driven "
                                 f"interrupt ({source}) is not simulated")
        count = int((self.time - self._boot_t0) * (rate or 0.0)) if enabled else 0
        return prio | ((count & 0x7FFFFFF) << 8) | (0x80000000 if enabled else 0)

    def _irq_enabled(self, irqn: int) -> bool:
        s = self._settings[None]
        by_config = {13: "config.enable_uart_a", 15: "config.enable_uart_a", 52: "config.enable_uart_a",
                     16: "config.enable_uart_b", 17: "config.enable_uart_b", 38: "config.enable_uart_b",
                     19: "config.enable_can_a", 20: "config.enable_can_a", 21: "config.enable_can_a",
                     22: "config.enable_can_a"}
        key = by_config.get(irqn)
        return True if key is None else bool(s.get(key, False))

    def _get_dma_status(self, stream: int) -> int:
        """main.cpp:487-505: 0 for a stream in reset, else configured | channel << 2 | prio."""
        stream = int(stream)
        if stream >= 16:
            return 0xFFFFFFFF
        if self.firmware == "0.5.1":
            raise UnmodeledError("odrv.get_dma_status: not modelled for fw 0.5.1")
        hit = DMA_056.get(stream)
        if hit is None:
            return 0
        channel, prio, _, when = hit
        if when != "always" and not self._settings[None].get(when, False):
            return 0
        return 0x80000000 | ((channel & 0x7) << 2) | (prio & 0x3)

    def _nothing_wired(self, a: int):
        """mechanical_brake.cpp: drives the brake's GPIO; nothing is wired to it here."""
        return None

    def _anticogging_value(self, a: int, index: int) -> float:
        return 0.0     # controller.hpp:87-89: the map is all zero (never calibrated)

    def _remove_anticogging_bias(self, a: int):
        return None    # controller.cpp: subtracts the map's mean: an all-zero map stays zero

    def _store_can_baud_rate(self, rate: int):
        self._settings[None]["can.config.baud_rate"] = int(rate)   # fw-v0.5.1 interface_can.cpp

    def _refuse(self, *args):
        """A function the model cannot run: raise at the call, naming it and why."""
        a, name, reason = (args[0], args[1], args[2]) if len(args) >= 3 and isinstance(args[0], int) \
            else (None, args[0], args[1])
        where = f"axis{a}.{name}" if a is not None else name
        raise UnmodeledError(f"odrv.{where}(): {reason}")

    # -- erase ---------------------------------------------------------------------------
    def _erase_configuration(self):
        """main.cpp:186-195: erase the stored configuration and reset: the board comes back
        with the firmware's defaults (fw-v0.5.1 main.cpp: the same, through NVM_erase)."""
        self.saved_configuration = None
        self.reboot()
        raise DeviceLostError("virtual ODrive: erase_configuration() reset the board; reconnect "
                              "(by serial number)")


def float32(value: float) -> float:
    """``value`` as the firmware stores a float."""
    return struct.unpack("<f", struct.pack("<f", value))[0]
