// Test wrapper: the packer and the framer with a frame memory and an IMU memory the cocotb test
// fills. wr_data is {im, re} as two 32-bit words; the core's sums are 28-bit, so are the memory's.
module tb_packer (
    input wire clk, input wire rst, input wire start,
    input wire [31:0] seq, input wire [63:0] ts, input wire [15:0] tx_mask, input wire [15:0] rx_mask,
    input wire [7:0] status,
    input wire [7:0] wr_addr, input wire [63:0] wr_data, input wire wr_en,
    input wire [3:0] imu_count, input wire [3:0] imu_base,
    input wire [6:0] imu_wr_addr, input wire [15:0] imu_wr_data, input wire imu_wr_en,
    output wire [7:0] out_data, output wire out_valid, output wire out_last, input wire out_ready,
    output wire busy
);
    reg [55:0] mem [0:255];
    reg [55:0] rd_data;
    wire [7:0] rd_addr;
    reg [15:0] imu_mem [0:127];
    reg [15:0] imu_rd;
    wire [6:0] imu_addr;
    always @(posedge clk) begin
        if (wr_en) mem[wr_addr] <= {wr_data[59:32], wr_data[27:0]};
        rd_data <= mem[rd_addr];
        if (imu_wr_en) imu_mem[imu_wr_addr] <= imu_wr_data;
        imu_rd <= imu_mem[imu_addr];
    end
    reg [2:0] tph = 0;  // the timestamp as the core streams it: byte tph of ts, LSB with ts_first
    always @(posedge clk) tph <= tph + 1;
    wire [7:0] pk_data; wire pk_valid, pk_last, pk_ready, pk_busy, fr_busy;
    tactile_packer u (.clk(clk), .rst(rst), .start(start), .seq(seq), .ts_byte(ts[8 * tph +: 8]),
        .ts_first(tph == 3'd0), .tx_mask(tx_mask),
        .rx_mask(rx_mask), .status(status), .imu_count(imu_count), .imu_base(imu_base), .rd_addr(rd_addr),
        .rd_data(rd_data), .imu_addr(imu_addr), .imu_data(imu_rd), .out_data(pk_data), .out_valid(pk_valid),
        .out_last(pk_last), .out_ready(pk_ready), .busy(pk_busy));
    tactile_framer u_fr (.clk(clk), .rst(rst), .a_data(8'd0), .a_valid(1'b0), .a_last(1'b0), .a_ready(),
        .b_data(pk_data), .b_valid(pk_valid), .b_last(pk_last), .b_ready(pk_ready),
        .tx_data(out_data), .tx_valid(out_valid), .tx_ready(out_ready), .busy(fr_busy), .tx_last(out_last));
    assign busy = pk_busy || fr_busy;
endmodule
