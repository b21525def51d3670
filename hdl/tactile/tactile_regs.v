// Configuration registers on the core's memory bus (map: docs/protocols/tactile.md).
// Status (0 ok, 1 bad address, 2 read-only) is combinational on the address; writes on we; the read
// value is registered and follows the address within 3 clocks (the command parser takes it much
// later). A block RAM holds the 16 frequency registers (entries 0..15) and a copy of the 16-bit
// registers (entry 16 + addr[4:2]), which are read back from it; the core uses flip-flop copies of
// those. The RAM's read port is shared: the DDS reads frequency freq_addr when freq_re (value in
// freq_q two clocks later), the bus reads in every other clock. After reset the RAM is loaded with
// the defaults (init high for 32 clocks).
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
    // 0x0000..0x001C: eight registers selected by addr[4:2]; id (0) and frame_count (6) read-only,
    // imu_enable (4) and run (5) one bit; 0x0100..0x013C: freq[addr[5:2]].
    wire is_reg = (addr[15:5] == 11'd0) && (addr[1:0] == 2'b00);
    wire is_freq = (addr[15:6] == 10'h004) && (addr[1:0] == 2'b00);
    wire [2:0] sel = addr[4:2];
    wire ro = is_reg && (sel == 3'd0 || sel == 3'd6);
    wire wide = is_reg && (sel == 3'd1 || sel == 3'd2 || sel == 3'd3 || sel == 3'd7);  // 16-bit, in the RAM
    always @* status = !(is_reg || is_freq) ? 8'd1 : (we && ro) ? 8'd2 : 8'd0;

    reg [5:0] ic;  // init counter: 0..31 loading defaults, 32 done
    assign init = !ic[5];
    reg [31:0] def;  // default of RAM entry ic
    always @* begin
        def = 32'd0;
        if (!ic[4]) def[31:24] = {3'd0, ic[3:0], 1'b0} + 8'd8;  // freq: (8 + 2k) << 24
        else case (ic[2:0])
            3'd1, 3'd7: def[15:0] = 16'd256;  // window, tick_div
            3'd2, 3'd3: def[15:0] = 16'hFFFF;  // tx_enable, rx_enable
            default: ;
        endcase
    end
    (* ram_style = "block", no_rw_check *) reg [31:0] ram [0:31];
    wire in_ram = is_freq || wide;
    wire [4:0] ra_bus = is_freq ? {1'b0, addr[5:2]} : {2'b10, sel};
    wire r_we = init || (we && in_ram);
    wire [4:0] r_wa = init ? ic[4:0] : ra_bus;
    wire [31:0] r_wd = init ? def : {is_freq ? wdata[31:16] : 16'd0, wdata[15:0]};  // truncated to 16 bits
    wire [4:0] r_ra = freq_re ? {1'b0, freq_addr} : ra_bus;
    reg [31:0] r_q; reg r_dds;
    always @(posedge clk) begin
        if (r_we) ram[r_wa] <= r_wd;
        r_q <= ram[r_ra];
        r_dds <= freq_re;
        if (r_dds) freq_q <= r_q;
    end

    reg [31:0] reg_q;  // registers not in the RAM
    always @* case (sel)
        3'd0: reg_q = 32'h58540002;
        3'd4: reg_q = {31'd0, imu_enable};
        3'd5: reg_q = {31'd0, run};
        3'd6: reg_q = frame_count;
        default: reg_q = 32'd0;
    endcase
    always @(posedge clk) begin
        if (!in_ram) rdata <= is_reg ? reg_q : 32'd0;
        else if (!r_dds) rdata <= r_q;  // else keep: the DDS had the port
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
