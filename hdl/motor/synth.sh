#!/bin/sh
# Synthesis report for the motor-control core (one axis, hdl/motor/README.md):
#  1. yosys 0.23 synth_ecp5 of motor_axis for the board's LFE5U-12F (resource counts);
#  2. an Fmax bound: fmax_wrapper (axis + configuration shift register) through synth_ice40 -dsp
#     and nextpnr-ice40 on an iCE40 UP5K, since nextpnr-ecp5 is not packaged in Debian.
# Logs in hdl/motor/build/.  Run: sh hdl/motor/synth.sh   (about 2 minutes)
set -e
cd "$(dirname "$0")"
mkdir -p build
SRC="motor_axis.v motor_watchdog.v encoder_spi.v pid_axis.v commutation.v sine_rom.v pwm_center.v"
yosys -q -l build/ecp5.log -p "read_verilog $SRC; synth_ecp5 -top motor_axis -json build/motor_ecp5.json; stat" \
    >/dev/null
sed -n '/Printing statistics/,$p' build/ecp5.log | grep -E "LUT4|TRELLIS_FF|CCU2C|MULT18X18D|DP16KD|L6MUX|PFUMX" \
    | sort -u
if command -v nextpnr-ice40 >/dev/null; then
    yosys -q -l build/ice40.log -p "read_verilog $SRC fmax_wrapper.v; synth_ice40 -dsp -top fmax_wrapper \
        -json build/fmax_ice40.json" >/dev/null
    nextpnr-ice40 --up5k --package sg48 --json build/fmax_ice40.json --freq 50 --pcf-allow-unconstrained \
        --seed 1 --log build/nextpnr_ice40.log >/dev/null 2>&1 || echo "nextpnr-ice40 failed: see build/"
    grep -E "ICESTORM_LC:|SB_MAC16|Max frequency" build/nextpnr_ice40.log | tail -4
fi
