#!/bin/sh
# Synthesis reports with yosys (0.23): the glove core on the LFE5U-12F (ECP5, 16 x 16 lines) and a
# 4 x 4 fingertip variant on the iCE40, then an Fmax estimate of the iCE40 variant with
# nextpnr-ice40 (if installed) on an HX8K and an UP5K; nextpnr-ecp5 is not packaged in Debian.
# ECP5 twice: -nowidelut (the figure in hdl/README.md: LUT4 only) and the default mapping (wide
# functions as LUT4 + PFUMX/L6MUX21). Logs and netlists in hdl/tactile/build/; run from anywhere
# (about 1.5 minutes). Not called by the tests.
set -e
cd "$(dirname "$0")"
mkdir -p build
SRC="tactile_core.v tactile_packer.v tactile_regs.v tactile_cmd.v tactile_framer.v uart.v crc32.v"
ECP5="chparam -set NTX 16 -set NRX 16 tactile_core; synth_ecp5 -top tactile_core"
yosys -q -l build/ecp5.log -p "read_verilog $SRC; $ECP5 -nowidelut; stat" >/dev/null
yosys -q -l build/ecp5_widelut.log -p "read_verilog $SRC; $ECP5; stat" >/dev/null
yosys -q -l build/ice40.log -p "read_verilog $SRC; chparam -set NTX 4 -set NRX 4 tactile_core; \
    synth_ice40 -top tactile_core -json build/tactile_ice40.json; stat" >/dev/null
# the last statistics block of each log
stats() { awk '/Printing statistics/{n++; s=""} {s=s $0 "\n"} END{printf "%s", s}' "$1" \
    | grep -E "^ +[A-Z][A-Z0-9_]+ +[0-9]+$" | sed "s/^ */$2 /"; }
stats build/ecp5.log ecp5
stats build/ecp5_widelut.log ecp5-widelut
stats build/ice40.log ice40
if command -v nextpnr-ice40 >/dev/null; then
    for dev in "hx8k ct256" "up5k sg48"; do
        set -- $dev
        nextpnr-ice40 --$1 --package $2 --json build/tactile_ice40.json --freq 48 --pcf-allow-unconstrained \
            --timing-allow-fail --seed 1 --log build/nextpnr_$1.log >/dev/null 2>&1 || echo "nextpnr-ice40 --$1 failed"
        { grep -E "ICESTORM_LC:|ICESTORM_RAM:" build/nextpnr_$1.log; grep "Max frequency" build/nextpnr_$1.log | tail -1; } \
            | sed -E "s/^(Info|Warning): *//; s/^/$1 /"
    done
fi
