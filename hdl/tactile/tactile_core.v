// Tactile readout core (thesis 4.5.5): DDS sine excitations -> first-order delta-sigma DAC
// bitstreams on NTX lines; current-mode delta-sigma ADC loops on NRX lines (comparator and
// integrator are analog, outside: adc_cmp in, adc_fb feedback out); the tactile processor
// correlates each ADC bitstream with sine and cosine of every excitation frequency over a window
// into a complex frame (double-buffered), packed and sent over the UART with register access.
module tactile_core #(
    parameter NTX = 16, parameter NRX = 16,
    parameter UART_DIV = 4, parameter CLK_PER_US = 48,
    parameter LUT_FILE = "sine_lut.hex"
) (
    input  wire clk, input wire rst,
    input  wire uart_rx, output wire uart_tx,
    output reg  [NTX-1:0] dac_out,
    input  wire [NRX-1:0] adc_cmp, output reg [NRX-1:0] adc_fb,
    output reg  strobe
);
    // ---- registers, command parser, UART ----
    wire [15:0] bus_addr; wire [31:0] bus_wdata, bus_rdata; wire bus_we; wire [7:0] bus_status;
    wire [15:0] window, tx_enable, rx_enable, tick_div; wire imu_enable, run, written;
    wire [511:0] freq_flat;
    reg [31:0] seq;
    tactile_regs u_regs (.clk(clk), .rst(rst), .addr(bus_addr), .wdata(bus_wdata), .we(bus_we),
        .rdata(bus_rdata), .status(bus_status), .frame_count(seq - 1), .window(window),
        .tx_enable(tx_enable), .rx_enable(rx_enable), .imu_enable(imu_enable), .run(run),
        .tick_div(tick_div), .freq_flat(freq_flat), .written(written));
    wire [7:0] rx_byte; wire rx_valid;
    uart_rx #(.DIV(UART_DIV)) u_rx (.clk(clk), .rst(rst), .rx(uart_rx), .data(rx_byte), .valid(rx_valid));
    wire [7:0] cmd_data; wire cmd_valid, cmd_last; wire cmd_ready; wire [15:0] rejected;
    tactile_cmd u_cmd (.clk(clk), .rst(rst), .rx_data(rx_byte), .rx_valid(rx_valid), .bus_addr(bus_addr),
        .bus_wdata(bus_wdata), .bus_we(bus_we), .bus_rdata(bus_rdata), .bus_status(bus_status),
        .out_data(cmd_data), .out_valid(cmd_valid), .out_last(cmd_last), .out_ready(cmd_ready),
        .rejected(rejected));
    wire [7:0] pk_data; wire pk_valid, pk_last, pk_ready, pk_busy;
    wire [7:0] tx_byte; wire tx_valid, tx_ready;
    reg [1:0] owner;  // 0 none, 1 reply, 2 frame: a frame is never interleaved
    assign tx_valid = (owner == 1) ? cmd_valid : (owner == 2) ? pk_valid : 1'b0;
    assign tx_byte = (owner == 1) ? cmd_data : pk_data;
    assign cmd_ready = (owner == 1) && tx_ready;
    assign pk_ready = (owner == 2) && tx_ready;
    always @(posedge clk) begin
        if (rst) owner <= 0;
        else if (owner == 0) owner <= cmd_valid ? 2'd1 : pk_valid ? 2'd2 : 2'd0;
        else if (tx_valid && tx_ready && ((owner == 1) ? cmd_last : pk_last)) owner <= 0;
    end
    uart_tx #(.DIV(UART_DIV)) u_tx (.clk(clk), .rst(rst), .data(tx_byte), .valid(tx_valid), .ready(tx_ready),
        .tx(uart_tx));

    // ---- device time in microseconds ----
    reg [63:0] time_us; reg [15:0] us_div;
    always @(posedge clk) begin
        if (rst) begin time_us <= 0; us_div <= 0; end
        else if (us_div == CLK_PER_US - 1) begin us_div <= 0; time_us <= time_us + 1; end
        else us_div <= us_div + 1;
    end

    // ---- sample ticks ----
    localparam MIN_DIV = NTX * NRX + 4;
    wire [15:0] div = (tick_div < MIN_DIV) ? MIN_DIV : tick_div;
    reg [15:0] tcnt, wcnt;
    reg active; reg [3:0] kk, jj;
    reg bank;
    // ---- sine table, DDS, DAC state ----
    reg signed [11:0] lut [0:255];
    initial $readmemh(LUT_FILE, lut);
    reg [31:0] phase [0:NTX-1];
    reg signed [12:0] dac_acc [0:NTX-1];
    reg signed [11:0] sin_q, cos_q;
    // ---- frame memory: two banks of 256 x {im, re}; the processor owns `bank`, the packer the other ----
    reg [63:0] mem0 [0:255]; reg [63:0] mem1 [0:255];
    reg [63:0] rd0, rd1; reg bank_d;
    wire [7:0] pk_addr;
    wire [7:0] pr_addr = {kk, jj};
    reg s1_valid; reg [3:0] s1_k, s1_j; reg s1_first;
    reg [63:0] wdata; reg we; reg [7:0] waddr;
    wire [7:0] sin_idx = (kk < NTX) ? phase[kk][31:24] : 8'd0;
    wire [7:0] cos_idx = sin_idx + 8'd64;  // 8-bit wrap: a quarter turn later
    wire [63:0] pr_rdata = bank_d ? rd1 : rd0;
    wire [63:0] pk_rdata = bank_d ? rd0 : rd1;
    always @(posedge clk) begin
        if (we && !bank) mem0[waddr] <= wdata;
        if (we && bank) mem1[waddr] <= wdata;
        rd0 <= mem0[bank ? pk_addr : pr_addr];
        rd1 <= mem1[bank ? pr_addr : pk_addr];
        bank_d <= bank;
        sin_q <= lut[sin_idx];
        cos_q <= lut[cos_idx];
    end

    wire signed [31:0] acc_re = s1_first ? 32'sd0 : $signed(pr_rdata[31:0]);
    wire signed [31:0] acc_im = s1_first ? 32'sd0 : $signed(pr_rdata[63:32]);
    wire fbit = adc_fb[s1_j];
    wire signed [12:0] dac_v = dac_acc[s1_k] + (tx_enable[s1_k] ? {sin_q[11], sin_q} : 13'sd0);
    reg first_tick, cfg_changed, dropped;
    reg pk_start;
    integer i;
    always @(posedge clk) begin
        strobe <= 1'b0; we <= 1'b0; pk_start <= 1'b0;
        if (rst) begin
            tcnt <= 0; wcnt <= 0; active <= 0; bank <= 0; seq <= 0; first_tick <= 1; s1_valid <= 0;
            cfg_changed <= 0; dropped <= 0; adc_fb <= 0; dac_out <= 0;
            for (i = 0; i < NTX; i = i + 1) begin phase[i] <= 0; dac_acc[i] <= 0; end
        end else begin
            if (written) cfg_changed <= 1'b1;
            tcnt <= (tcnt >= div - 1) ? 16'd0 : tcnt + 1;
            if (tcnt == 0) begin  // sample the comparators; their bits are the ADC output and feedback
                adc_fb <= adc_cmp; strobe <= 1'b1; active <= 1'b1; kk <= 0; jj <= 0;
            end else if (active) begin
                if (jj == NRX - 1) begin
                    jj <= 0; kk <= kk + 1;
                    if (kk == NTX - 1) active <= 1'b0;
                end else jj <= jj + 1;
            end
            // stage 0 -> 1
            s1_valid <= active && tcnt != 0; s1_k <= kk; s1_j <= jj; s1_first <= first_tick;
            if (s1_valid) begin  // stage 1: accumulate, write back
                we <= 1'b1; waddr <= {s1_k, s1_j};
                wdata[31:0] <= acc_re + (fbit ? sin_q : -sin_q);
                wdata[63:32] <= acc_im + (fbit ? cos_q : -cos_q);
                if (s1_j == 0) begin
                    dac_out[s1_k] <= (dac_v >= 0);
                    dac_acc[s1_k] <= dac_v - ((dac_v >= 0) ? 13'sd2048 : -13'sd2048);
                end
                if (s1_j == NRX - 1) phase[s1_k] <= phase[s1_k] + freq_flat[32 * s1_k +: 32];
            end
            if (tcnt == div - 1) begin  // end of a sample tick
                first_tick <= 1'b0;
                if (wcnt >= window - 1) begin  // end of the window: hand the bank to the packer
                    wcnt <= 0; first_tick <= 1'b1; bank <= ~bank; seq <= seq + 1;
                    cfg_changed <= written; dropped <= 1'b0;
                    if (run && !pk_busy) pk_start <= 1'b1;
                    else if (run) dropped <= 1'b1;
                end else wcnt <= wcnt + 1;
            end
        end
    end
    reg [7:0] pk_status;
    wire [15:0] tx_mask = tx_enable & ((17'd1 << NTX) - 17'd1);
    wire [15:0] rx_mask = rx_enable & ((17'd1 << NRX) - 17'd1);
    always @(posedge clk) if (tcnt == div - 1 && wcnt >= window - 1) pk_status <= {5'd0, dropped, cfg_changed, 1'b0};
    tactile_packer u_pk (.clk(clk), .rst(rst), .start(pk_start), .seq(seq - 1), .ts(time_us),
        .tx_mask(tx_mask), .rx_mask(rx_mask),
        .status(pk_status), .rd_addr(pk_addr), .rd_data(pk_rdata), .out_data(pk_data), .out_valid(pk_valid),
        .out_last(pk_last), .out_ready(pk_ready), .busy(pk_busy));
endmodule
