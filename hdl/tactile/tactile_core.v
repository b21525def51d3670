// Tactile readout core (thesis 4.5.5): DDS sine excitations -> first-order delta-sigma DAC
// bitstreams on NTX lines; current-mode delta-sigma ADC loops on NRX lines (comparator and
// integrator are analog, outside: adc_cmp in, adc_fb feedback out); the tactile processor
// correlates each ADC bitstream with sine and cosine of every excitation frequency over a window
// into a complex frame (double-buffered), packed and sent over the UART with register access.
// IMU samples (6 x i16 words as the protocol carries them: ax ay az gx gy gz) come in on imu_*:
// one word per imu_valid, imu_first on the first word of a sample; with imu_enable set, a frame
// carries the last (at most 8) samples completed during its window (status bit 3 if more came).
//
// Area: per-line state (DDS phase, DAC integrator), the frequency registers and the frame banks are
// block RAM; one cell per clock, 28-bit correlation sums (|sum| <= 65536 x 2047 < 2^27).
module tactile_core #(
    parameter NTX = 16, parameter NRX = 16,
    parameter UART_DIV = 4, parameter CLK_PER_US = 48,
    parameter LUT_FILE = "sine_lut.hex"
) (
    input  wire clk, input wire rst,
    input  wire uart_rx, output wire uart_tx,
    output reg  [NTX-1:0] dac_out,
    input  wire [NRX-1:0] adc_cmp, output reg [NRX-1:0] adc_fb,
    output reg  strobe,
    input  wire imu_valid, input wire imu_first, input wire [15:0] imu_data
);
    // ---- registers, command parser, UART, framing ----
    wire [15:0] bus_addr; wire [31:0] bus_wdata, bus_rdata; wire bus_we; wire [7:0] bus_status;
    wire [15:0] window, tx_enable, rx_enable, tick_div; wire imu_enable, run, written, init;
    reg [31:0] fc;  // sequence number of the last frame (all ones before the first)
    reg [3:0] kk, jj; reg active;
    reg s1_v, s2_v; reg [3:0] s1_k, s1_j, s2_k, s2_j;
    wire line_re = active && (jj == 4'd0);  // stage 0 of a line's first cell: fetch its state
    wire [31:0] freq_q;
    tactile_regs u_regs (.clk(clk), .rst(rst), .addr(bus_addr), .wdata(bus_wdata), .we(bus_we),
        .rdata(bus_rdata), .status(bus_status), .frame_count(fc), .window(window),
        .tx_enable(tx_enable), .rx_enable(rx_enable), .imu_enable(imu_enable), .run(run),
        .tick_div(tick_div), .freq_addr(kk), .freq_re(line_re), .freq_q(freq_q), .written(written),
        .init(init));
    wire [7:0] rx_byte; wire rx_valid;
    uart_rx #(.DIV(UART_DIV)) u_rx (.clk(clk), .rst(rst), .rx(uart_rx), .data(rx_byte), .valid(rx_valid));
    wire [7:0] cmd_data; wire cmd_valid, cmd_last, cmd_ready; wire [15:0] rejected;
    tactile_cmd u_cmd (.clk(clk), .rst(rst), .rx_data(rx_byte), .rx_valid(rx_valid), .bus_addr(bus_addr),
        .bus_wdata(bus_wdata), .bus_we(bus_we), .bus_rdata(bus_rdata), .bus_status(bus_status),
        .out_data(cmd_data), .out_valid(cmd_valid), .out_last(cmd_last), .out_ready(cmd_ready),
        .rejected(rejected));
    wire [7:0] pk_data; wire pk_valid, pk_last, pk_ready, pk_busy;
    wire [7:0] tx_byte; wire tx_valid, tx_ready;
    tactile_framer u_fr (.clk(clk), .rst(rst), .a_data(cmd_data), .a_valid(cmd_valid), .a_last(cmd_last),
        .a_ready(cmd_ready), .b_data(pk_data), .b_valid(pk_valid), .b_last(pk_last), .b_ready(pk_ready),
        .tx_data(tx_byte), .tx_valid(tx_valid), .tx_ready(tx_ready), .busy(), .tx_last());
    uart_tx #(.DIV(UART_DIV)) u_tx (.clk(clk), .rst(rst), .data(tx_byte), .valid(tx_valid), .ready(tx_ready),
        .tx(uart_tx));

    // ---- device time in microseconds: 8 bytes rotating (one byte a clock) through an 8-bit
    // incrementer; a microsecond tick is added as the least significant byte passes (tph 0), the
    // carry follows it through the other 7. The packer takes the bytes from the stream (ts_byte,
    // least significant first from tph 0). Needs CLK_PER_US >= 8.
    localparam UW = (CLK_PER_US > 2) ? $clog2(CLK_PER_US) : 1;
    reg [63:0] tsr; reg [2:0] tph; reg tcar, tinc; reg [UW-1:0] us_div;
    wire us_tick = (us_div == CLK_PER_US - 1);
    wire [8:0] tsum = {1'b0, tsr[7:0]} + {8'd0, (tph == 3'd0) ? tinc : tcar};
    always @(posedge clk) begin
        if (rst) begin tsr <= 0; tph <= 0; tcar <= 0; tinc <= 0; us_div <= 0; end
        else begin
            tsr <= {tsum[7:0], tsr[63:8]}; tph <= tph + 1; tcar <= tsum[8];
            us_div <= us_tick ? 0 : us_div + 1;
            if (tph == 3'd0) tinc <= us_tick;
            else if (us_tick) tinc <= 1'b1;
        end
    end
    initial if (CLK_PER_US < 8) $display("tactile_core: CLK_PER_US must be at least 8");

    // ---- sample ticks (div clocks) and windows (window ticks): down counters ----
    // A tick: clock 0 samples the comparators, cells run in clocks 1..NTX*NRX (stage 0), the last
    // write lands in clock NTX*NRX + 2. tick_div and window take effect at the next tick / window.
    wire hold = rst || init;
    localparam integer MIN_DIV = NTX * NRX + 4;
    localparam [15:0] DIV_MIN = MIN_DIV;
    localparam [15:0] DIV_RST = (MIN_DIV > 256) ? MIN_DIV : 256;  // tick_div resets to 256
    wire [15:0] div = (tick_div < DIV_MIN) ? DIV_MIN : tick_div;
    reg [15:0] td, wd;  // clocks left in this tick, ticks left in this window (0: 65536)
    reg tick0;          // first clock of a tick
    reg fresh;          // first tick after reset: line state reads as zero
    wire tick_end = (td == 16'd1);
    wire win_end = tick_end && (wd == 16'd1);
    always @(posedge clk) begin
        if (hold) begin td <= DIV_RST; wd <= 16'd256; tick0 <= 1'b1; fresh <= 1'b1; end
        else begin
            tick0 <= tick_end;
            td <= tick_end ? div : td - 1;
            if (tick_end) begin fresh <= 1'b0; wd <= (wd == 16'd1) ? window : wd - 1; end
        end
    end

    // ---- processor pipeline: stage 0 cell counter, 1 reads, 2 accumulate and write ----
    always @(posedge clk) begin
        strobe <= 1'b0;
        s1_v <= active; s1_k <= kk; s1_j <= jj;
        s2_v <= s1_v; s2_k <= s1_k; s2_j <= s1_j;
        if (hold) begin
            active <= 1'b0; s1_v <= 1'b0; s2_v <= 1'b0; adc_fb <= 0; kk <= 0; jj <= 0;
        end else if (tick0) begin  // sample the comparators; their bits are the ADC output and feedback
            adc_fb <= adc_cmp; strobe <= 1'b1; active <= 1'b1; kk <= 0; jj <= 0;
        end else if (active) begin
            if (jj == NRX - 1) begin
                jj <= 0; kk <= kk + 1;
                if (kk == NTX - 1) active <= 1'b0;
            end else jj <= jj + 1;
        end
    end

    reg [44:0] line_q;
    reg [11:0] sin_q, cos_q;
    wire signed [12:0] dacc = line_q[44:32];
    wire signed [12:0] dac_v = dacc + (tx_enable[s2_k] ? {sin_q[11], sin_q} : 13'sd0);
    wire dac_pos = !dac_v[12];
    wire [12:0] dac_n = {dac_v[12:11] + (dac_pos ? 2'b11 : 2'b01), dac_v[10:0]};  // -+ 2048
    wire [44:0] line_wd = {dac_n, line_q[31:0] + freq_q};

    // Line state {DAC integrator, DDS phase}: read at stage 0 of a line's first cell, written back
    // (phase + freq, integrator - feedback) at its stage 2.
    (* ram_style = "block", no_rw_check *) reg [44:0] line [0:15];
    always @(posedge clk) begin
        if (s2_v && s2_j == 4'd0) line[s2_k] <= line_wd;
        if (fresh) line_q <= 45'd0;
        else if (line_re) line_q <= line[kk];
    end
    // Sine table: sine and cosine of the line's phase, from stage 1 on (stable for the whole line).
    reg [11:0] lut [0:255];
    initial $readmemh(LUT_FILE, lut);
    wire [7:0] sin_idx = line_q[31:24];
    wire [7:0] cos_idx = sin_idx + 8'd64;  // 8-bit wrap: a quarter turn later
    always @(posedge clk) begin
        sin_q <= lut[sin_idx];
        cos_q <= lut[cos_idx];
    end
    always @(posedge clk) begin
        if (rst) dac_out <= 0;
        else if (s2_v && s2_j == 4'd0) dac_out[s2_k] <= dac_pos;
    end

    // ---- frame memory: two banks of 256 x {im, re} in one array; the processor owns `bank`, the
    // packer the other. Two read ports: yosys keeps one copy of the array per read port (both written),
    // so neither port needs a bank multiplexer. The processor's read is zero in the first tick of a
    // window (the block RAM's output reset).
    localparam KB = (NTX > 1) ? $clog2(NTX) : 1;  // cell address bits actually used
    localparam JB = (NRX > 1) ? $clog2(NRX) : 1;
    reg bank;
    (* no_rw_check *) reg [55:0] fmem [0:(2 << (KB + JB)) - 1];
    reg [55:0] pr_q, pk_q;
    wire [7:0] pk_addr;
    reg first_tick;
    wire fbit = adc_fb[s2_j];
    wire [27:0] sin28 = {{16{sin_q[11]}}, sin_q};
    wire [27:0] cos28 = {{16{cos_q[11]}}, cos_q};
    // acc + (fbit ? s : -s) as acc + (s ^ ~fbit) + ~fbit: one carry chain each
    wire [27:0] sum_re = pr_q[27:0] + (sin28 ^ {28{~fbit}}) + {27'd0, ~fbit};
    wire [27:0] sum_im = pr_q[55:28] + (cos28 ^ {28{~fbit}}) + {27'd0, ~fbit};
    always @(posedge clk) begin
        if (s2_v) fmem[{bank, s2_k[KB-1:0], s2_j[JB-1:0]}] <= {sum_im, sum_re};
        if (first_tick) pr_q <= 56'd0;
        else pr_q <= fmem[{bank, s1_k[KB-1:0], s1_j[JB-1:0]}];
        pk_q <= fmem[{~bank, pk_addr[4+KB-1:4], pk_addr[JB-1:0]}];  // the packer reads enabled cells only
    end

    // ---- IMU samples: a ring of 16 slots x 8 words (6 used) ----
    (* no_rw_check *) reg [15:0] imu_mem [0:127];
    reg [15:0] imu_q;
    wire [6:0] pk_iaddr;
    reg in_smp; reg [2:0] iw; reg [3:0] wslot, pend;  // pend: samples completed this window, saturating at 9
    wire iv = imu_valid && imu_enable && !hold;
    wire i_done = iv && !imu_first && in_smp && (iw == 3'd5);
    always @(posedge clk) begin
        if (iv && (imu_first || in_smp)) imu_mem[{wslot, imu_first ? 3'd0 : iw}] <= imu_data;
        imu_q <= imu_mem[pk_iaddr];
    end
    always @(posedge clk) begin
        if (hold) begin in_smp <= 1'b0; wslot <= 0; pend <= 0; end
        else begin
            if (!imu_enable) in_smp <= 1'b0;
            else if (imu_valid) begin
                if (imu_first) begin in_smp <= 1'b1; iw <= 3'd1; end
                else if (in_smp) begin
                    iw <= iw + 1;
                    if (iw == 3'd5) begin in_smp <= 1'b0; wslot <= wslot + 1; end
                end
            end
            if (win_end) pend <= {3'd0, i_done};
            else if (i_done && pend != 4'd9) pend <= pend + 1;
        end
    end

    // ---- windows: hand the finished bank to the packer ----
    reg cfg_changed, dropped, pk_start;
    reg [7:0] pk_status; reg [3:0] imu_n, imu_base;
    wire [3:0] n_take = !imu_enable ? 4'd0 : (pend > 4'd8) ? 4'd8 : pend;
    always @(posedge clk) begin
        pk_start <= 1'b0;
        if (hold) begin
            bank <= 0; fc <= 32'hFFFFFFFF; first_tick <= 1'b1; cfg_changed <= 0; dropped <= 0;
        end else begin
            if (written) cfg_changed <= 1'b1;
            if (tick_end) begin
                first_tick <= 1'b0;
                if (win_end) begin
                    first_tick <= 1'b1; fc <= fc + 1;
                    pk_status <= {4'd0, imu_enable && pend > 4'd8, dropped, cfg_changed, 1'b0};
                    imu_n <= n_take; imu_base <= wslot - n_take;
                    cfg_changed <= written; dropped <= 1'b0;
                    // A busy packer keeps its bank (this window's sums are dropped, the sequence skips).
                    if (run && !pk_busy) begin pk_start <= 1'b1; bank <= ~bank; end
                    else if (run) dropped <= 1'b1;
                end
            end
        end
    end
    wire [15:0] tx_mask = tx_enable & ((17'd1 << NTX) - 17'd1);
    wire [15:0] rx_mask = rx_enable & ((17'd1 << NRX) - 17'd1);
    tactile_packer u_pk (.clk(clk), .rst(rst), .start(pk_start), .seq(fc), .ts_byte(tsum[7:0]),
        .ts_first(tph == 3'd0), .tx_mask(tx_mask), .rx_mask(rx_mask), .status(pk_status), .imu_count(imu_n),
        .imu_base(imu_base), .rd_addr(pk_addr), .rd_data(pk_q), .imu_addr(pk_iaddr), .imu_data(imu_q),
        .out_data(pk_data), .out_valid(pk_valid), .out_last(pk_last), .out_ready(pk_ready), .busy(pk_busy));
endmodule
