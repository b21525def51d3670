// Test wrapper: the packer with a frame memory the cocotb test fills.
module tb_packer (
    input wire clk, input wire rst, input wire start,
    input wire [31:0] seq, input wire [63:0] ts, input wire [15:0] tx_mask, input wire [15:0] rx_mask,
    input wire [7:0] status,
    input wire [7:0] wr_addr, input wire [63:0] wr_data, input wire wr_en,
    output wire [7:0] out_data, output wire out_valid, output wire out_last, input wire out_ready,
    output wire busy
);
    reg [63:0] mem [0:255];
    reg [63:0] rd_data;
    wire [7:0] rd_addr;
    always @(posedge clk) begin
        if (wr_en) mem[wr_addr] <= wr_data;
        rd_data <= mem[rd_addr];
    end
    tactile_packer u (.clk(clk), .rst(rst), .start(start), .seq(seq), .ts(ts), .tx_mask(tx_mask),
        .rx_mask(rx_mask), .status(status), .rd_addr(rd_addr), .rd_data(rd_data), .out_data(out_data),
        .out_valid(out_valid), .out_last(out_last), .out_ready(out_ready), .busy(busy));
endmodule
