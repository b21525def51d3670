// Configuration registers on the core's memory bus (map: docs/protocols/tactile.md).
// Status (0 ok, 1 bad address, 2 read-only) is combinational on the address; writes on we; the read
// value is registered and follows the address within 3 clocks (the command parser takes it much
// later). The 16 frequency registers live in a block RAM whose read port is shared: the DDS reads
// line freq_addr when freq_re (value in freq_q two clocks later), the bus reads in every other clock.
// After reset the RAM is loaded with the default frequencies (init high for 16 clocks).
module tactile_regs (
    input  wire clk, input wire rst,
    input  wire [15:0] addr, input wire [31:0] wdata, input wire we,
    output reg  [31:0] rdata, output reg [7:0] status,
    input  wire [31:0] frame_count,
    output reg  [15:0] window, output reg [15:0] tx_enable, output reg [15:0] rx_enable,
    output reg  imu_enable, output reg run, output reg [15:0] tick_div,
    input  wire [3:0] freq_addr, input wire freq_re, output reg [31:0] freq_q,
    output reg  written, output wire init
);
    reg [4:0] ic;  // init counter: 0..15 loading defaults, 16 done
    assign init = !ic[4];
    wire is_freq = (addr[15:6] == 10'h004) && (addr[1:0] == 2'b00);  // 0x0100..0x013C

    (* ram_style = "block", no_rw_check *) reg [31:0] freq [0:15];
    wire f_we = init || (we && is_freq);
    wire [3:0] f_wa = init ? ic[3:0] : addr[5:2];
    wire [7:0] f_def = {3'd0, ic[3:0], 1'b0} + 8'd8;  // (8 + 2k) << 24
    wire [31:0] f_wd = init ? {f_def, 24'd0} : wdata;
    wire [3:0] f_ra = freq_re ? freq_addr : addr[5:2];
    reg [31:0] f_q; reg f_dds;
    always @(posedge clk) begin
        if (f_we) freq[f_wa] <= f_wd;
        f_q <= freq[f_ra];
        f_dds <= freq_re;
        if (f_dds) freq_q <= f_q;
    end

    // 0x0000..0x001C: eight registers selected by addr[4:2]; id (0) and frame_count (6) read-only.
    wire is_reg = (addr[15:5] == 11'd0) && (addr[1:0] == 2'b00);
    wire [2:0] sel = addr[4:2];
    wire ro = is_reg && (sel == 3'd0 || sel == 3'd6);
    always @* status = !(is_reg || is_freq) ? 8'd1 : (we && ro) ? 8'd2 : 8'd0;
    reg [31:0] reg_q;
    always @* case (sel)
        3'd0: reg_q = 32'h58540002;
        3'd1: reg_q = {16'd0, window};
        3'd2: reg_q = {16'd0, tx_enable};
        3'd3: reg_q = {16'd0, rx_enable};
        3'd4: reg_q = {31'd0, imu_enable};
        3'd5: reg_q = {31'd0, run};
        3'd6: reg_q = frame_count;
        default: reg_q = {16'd0, tick_div};
    endcase
    always @(posedge clk) begin
        if (!is_freq) rdata <= is_reg ? reg_q : 32'd0;
        else if (!f_dds) rdata <= f_q;  // else keep: the DDS had the port
    end

    wire wr = we && is_reg && !ro;
    always @(posedge clk) begin
        written <= 1'b0;
        if (rst) begin
            window <= 16'd256; tx_enable <= 16'hFFFF; rx_enable <= 16'hFFFF; imu_enable <= 1'b0;
            run <= 1'b1; tick_div <= 16'd256; ic <= 0;
        end else begin
            if (init) ic <= ic + 1;
            if (wr || (we && is_freq)) written <= 1'b1;
            if (wr) case (sel)
                3'd1: window <= wdata[15:0];
                3'd2: tx_enable <= wdata[15:0];
                3'd3: rx_enable <= wdata[15:0];
                3'd4: imu_enable <= wdata[0];
                3'd5: run <= wdata[0];
                3'd7: tick_div <= wdata[15:0];
                default: ;
            endcase
        end
    end
endmodule
