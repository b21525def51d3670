// Configuration registers on the core's memory bus (map: docs/protocols/tactile.md).
// Combinational read with a status (0 ok, 1 bad address, 2 read-only); writes on we.
module tactile_regs (
    input  wire clk, input wire rst,
    input  wire [15:0] addr, input wire [31:0] wdata, input wire we,
    output reg  [31:0] rdata, output reg [7:0] status,
    input  wire [31:0] frame_count,
    output reg  [15:0] window, output reg [15:0] tx_enable, output reg [15:0] rx_enable,
    output reg  imu_enable, output reg run, output reg [15:0] tick_div,
    output wire [511:0] freq_flat,
    output reg  written
);
    reg [31:0] freq [0:15];
    genvar g;
    generate for (g = 0; g < 16; g = g + 1) begin : flat
        assign freq_flat[32 * g +: 32] = freq[g];
    end endgenerate

    wire is_freq = (addr[15:6] == 10'h004) && (addr[1:0] == 2'b00);  // 0x0100..0x013C
    always @* begin
        status = 8'd0;
        rdata = 32'd0;
        if (is_freq) rdata = freq[addr[5:2]];
        else case (addr)
            16'h0000: begin rdata = 32'h58540002; status = we ? 8'd2 : 8'd0; end
            16'h0004: rdata = {16'd0, window};
            16'h0008: rdata = {16'd0, tx_enable};
            16'h000C: rdata = {16'd0, rx_enable};
            16'h0010: rdata = {31'd0, imu_enable};
            16'h0014: rdata = {31'd0, run};
            16'h0018: begin rdata = frame_count; status = we ? 8'd2 : 8'd0; end
            16'h001C: rdata = {16'd0, tick_div};
            default: status = 8'd1;
        endcase
    end

    integer i;
    always @(posedge clk) begin
        written <= 1'b0;
        if (rst) begin
            window <= 16'd256; tx_enable <= 16'hFFFF; rx_enable <= 16'hFFFF; imu_enable <= 1'b0;
            run <= 1'b1; tick_div <= 16'd256;
            for (i = 0; i < 16; i = i + 1) freq[i] <= (8 + 2 * i) << 24;
        end else if (we && status == 8'd0) begin
            written <= 1'b1;
            if (is_freq) freq[addr[5:2]] <= wdata;
            else case (addr)
                16'h0004: window <= wdata[15:0];
                16'h0008: tx_enable <= wdata[15:0];
                16'h000C: rx_enable <= wdata[15:0];
                16'h0010: imu_enable <= wdata[0];
                16'h0014: run <= wdata[0];
                16'h001C: tick_div <= wdata[15:0];
                default: ;
            endcase
        end
    end
endmodule
