// One motor axis of the control board (thesis 6.2): encoder readout, position/velocity PID,
// sinusoidal commutation, centre-aligned PWM with the current-sampling trigger, and the command
// watchdog. One control tick per PWM period (20 kHz): at the valley the encoder is read, the
// multi-turn position and the velocity (counts per tick) are updated, the PID runs, commutation
// turns its output into three phase voltages, and the duties apply from the next valley.
// The axis brakes (low sides on: windings shorted) when the watchdog expired, in brake mode, or
// while the encoder reports an error. Voltage mode: the ADC trigger is provided for the current
// readout, the current loop itself is not part of this core.
module motor_axis #(
    parameter CLK_PER_US = 50,
    parameter POLE_PAIRS = 4,
    parameter PWM_W = 11,
    parameter DEADTIME = 10,
    parameter SPI_HALF = 3
) (
    input wire clk,
    input wire rst,
    // command port, fed by the board's protocol decoder (a valid, CRC-checked command frame)
    input wire cmd_valid,
    input wire [2:0] cmd_mode,  // 0 brake, 1 position, 2 velocity, 3 effort (protocol Mode)
    input wire signed [31:0] cmd_pos,  // encoder counts
    input wire signed [15:0] cmd_vel,  // counts per control tick
    input wire signed [15:0] cmd_ff,  // PWM counts (effort mode: the whole output)
    // configuration registers
    input wire [23:0] watchdog_us,
    input wire [PWM_W-1:0] period_half,
    input wire [14:0] elec_offset,
    input wire [15:0] kp,
    input wire [15:0] ki,
    input wire [15:0] kd,
    input wire [15:0] i_clamp,
    // encoder
    output wire enc_cs_n,
    output wire enc_sclk,
    output wire enc_mosi,
    input wire enc_miso,
    // power stage
    output wire [2:0] gate_hi,
    output wire [2:0] gate_lo,
    output wire adc_trigger,
    // status for the feedback frame
    output reg signed [31:0] position,
    output reg signed [15:0] velocity,
    output wire braking,
    output wire wd_expired,
    output wire enc_error
);
    reg [2:0] mode;
    reg signed [31:0] pos_sp;
    reg signed [15:0] vel_sp, ff;
    always @(posedge clk) begin
        if (rst) begin
            mode <= 3'd0;
            pos_sp <= 0;
            vel_sp <= 0;
            ff <= 0;
        end else if (cmd_valid) begin
            mode <= cmd_mode;
            pos_sp <= cmd_pos;
            vel_sp <= cmd_vel;
            ff <= cmd_ff;
        end
    end

    wire [15:0] wd_trips;
    motor_watchdog #(.CLK_PER_US(CLK_PER_US)) wd (
        .clk(clk), .rst(rst), .kick(cmd_valid), .timeout_us(watchdog_us), .expired(wd_expired),
        .trips(wd_trips));

    // --- encoder and position -------------------------------------------------------------------
    wire period_start;
    wire [14:0] angle;
    wire angle_valid, angle_err, spi_busy;
    encoder_spi #(.HALF(SPI_HALF)) enc (
        .clk(clk), .rst(rst), .start(period_start), .cs_n(enc_cs_n), .sclk(enc_sclk), .mosi(enc_mosi),
        .miso(enc_miso), .angle(angle), .error(angle_err), .valid(angle_valid), .busy(spi_busy));

    reg have_angle, err_latched;
    reg [14:0] last_angle;
    reg signed [31:0] last_pos;
    wire signed [14:0] delta = angle - last_angle;  // shortest way round: |step| < half a turn
    assign enc_error = err_latched;
    reg pid_start;
    always @(posedge clk) begin
        pid_start <= 1'b0;
        if (rst) begin
            have_angle <= 1'b0;
            err_latched <= 1'b0;
            position <= 0;
            velocity <= 0;
            last_pos <= 0;
        end else if (angle_valid) begin
            err_latched <= angle_err;
            if (!angle_err) begin
                last_angle <= angle;
                if (!have_angle) begin
                    have_angle <= 1'b1;
                    position <= {17'd0, angle};
                    last_pos <= {17'd0, angle};
                end else begin
                    position <= position + delta;
                    last_pos <= position + delta;
                    velocity <= position + delta - last_pos;
                    pid_start <= 1'b1;
                end
            end
        end
    end

    // --- control --------------------------------------------------------------------------------
    assign braking = wd_expired || mode == 3'd0 || mode > 3'd3 || err_latched || !have_angle;
    wire signed [15:0] u;
    wire pid_done;
    reg [15:0] out_max;  // registered: configuration, not a timing path
    reg signed [15:0] ff_sat;
    always @(posedge clk) begin
        out_max <= {{(16 - PWM_W){1'b0}}, period_half} >> 1;
        ff_sat <= (ff > $signed(out_max)) ? $signed(out_max) : (ff < -$signed(out_max)) ? -$signed(out_max) : ff;
    end
    pid_axis pid (
        .clk(clk), .rst(rst), .start(pid_start), .velocity_mode(mode == 3'd2), .hold_i(braking),
        .pos_sp(pos_sp), .pos(position), .vel_sp(vel_sp), .vel(velocity), .ff(ff), .kp(kp), .ki(ki),
        .kd(kd), .i_clamp(i_clamp), .out_max(out_max), .u(u), .done(pid_done));

    wire signed [15:0] amplitude = braking ? 16'sd0 : (mode == 3'd3) ? ff_sat : u;
    wire signed [15:0] va, vb, vc;
    wire comm_done;
    commutation #(.POLE_PAIRS(POLE_PAIRS)) comm (
        .clk(clk), .rst(rst), .start(pid_done), .angle(last_angle), .offset(elec_offset),
        .amplitude(amplitude), .va(va), .vb(vb), .vc(vc), .done(comm_done));

    reg [PWM_W-1:0] duty_a, duty_b, duty_c;
    wire signed [16:0] mid = $signed({{(17 - PWM_W){1'b0}}, period_half}) >>> 1;
    always @(posedge clk) begin
        if (rst) begin
            duty_a <= 0;
            duty_b <= 0;
            duty_c <= 0;
        end else if (comm_done) begin
            duty_a <= mid + va;
            duty_b <= mid + vb;
            duty_c <= mid + vc;
        end
    end

    pwm_center #(.W(PWM_W), .DEADTIME(DEADTIME)) pwm (
        .clk(clk), .rst(rst), .period_half(period_half), .duty_a(duty_a), .duty_b(duty_b),
        .duty_c(duty_c), .brake(braking), .hi(gate_hi), .lo(gate_lo), .adc_trigger(adc_trigger),
        .period_start(period_start));
endmodule
