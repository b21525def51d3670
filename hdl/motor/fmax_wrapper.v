// Synthesis-only wrapper for the timing estimate: the axis's command and configuration inputs come
// from one shift register (on the board they are registers behind the protocol decoder), so the
// design fits a small package for place-and-route. Not used in simulation.
module fmax_wrapper (
    input wire clk,
    input wire rst,
    input wire sdi,
    input wire load,
    input wire enc_miso,
    output wire enc_cs_n,
    output wire enc_sclk,
    output wire enc_mosi,
    output wire [2:0] gate_hi,
    output wire [2:0] gate_lo,
    output wire adc_trigger,
    output wire status
);
    localparam N = 3 + 32 + 16 + 16 + 24 + 11 + 15 + 16 * 4;
    reg [N-1:0] sh;
    reg [N-1:0] cfg;
    reg cmd_valid;
    always @(posedge clk) begin
        sh <= {sh[N-2:0], sdi};
        cmd_valid <= load;
        if (load) cfg <= sh;
    end
    wire signed [31:0] position;
    wire signed [15:0] velocity;
    wire braking, wd_expired, enc_error;
    motor_axis axis (
        .clk(clk), .rst(rst), .cmd_valid(cmd_valid), .cmd_mode(cfg[2:0]), .cmd_pos(cfg[34:3]),
        .cmd_vel(cfg[50:35]), .cmd_ff(cfg[66:51]), .watchdog_us(cfg[90:67]), .period_half(cfg[101:91]),
        .elec_offset(cfg[116:102]), .kp(cfg[132:117]), .ki(cfg[148:133]), .kd(cfg[164:149]),
        .i_clamp(cfg[180:165]), .enc_cs_n(enc_cs_n), .enc_sclk(enc_sclk), .enc_mosi(enc_mosi),
        .enc_miso(enc_miso), .gate_hi(gate_hi), .gate_lo(gate_lo), .adc_trigger(adc_trigger),
        .position(position), .velocity(velocity), .braking(braking), .wd_expired(wd_expired),
        .enc_error(enc_error));
    assign status = braking ^ wd_expired ^ enc_error ^ (^position) ^ (^velocity);
endmodule
