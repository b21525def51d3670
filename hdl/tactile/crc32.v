// CRC-32 (IEEE 802.3, reflected, poly 0xEDB88320) one byte per call, as zlib.crc32.
// The running register holds the complemented CRC: start with 32'hFFFFFFFF, send ~crc LSB first.
module crc32_byte (
    input  wire [31:0] crc_in,
    input  wire [7:0]  data,
    output wire [31:0] crc_out
);
    function [31:0] step;
        input [31:0] c;
        input [7:0] d;
        integer i;
        reg [31:0] x;
        begin
            x = c ^ {24'd0, d};
            for (i = 0; i < 8; i = i + 1)
                x = x[0] ? ((x >> 1) ^ 32'hEDB88320) : (x >> 1);
            step = x;
        end
    endfunction
    assign crc_out = step(crc_in, data);
endmodule
